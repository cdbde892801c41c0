"""Camera calibration (paper §2.1): geometric (Zhang on ChArUco) and radiometric (response, colour)."""
