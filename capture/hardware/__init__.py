"""Light-stage hardware: strobe-controller protocol and driver, strobe sequences, camera interface."""
