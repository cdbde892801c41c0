"""Colour correction from a ColorChecker: the 3x3 matrix from linearised camera RGB to linear sRGB.

The chart hangs at the stage centre facing the cameras, lit by one strobe of known
direction ``ω`` and calibrated irradiance ``E`` (RGB). A patch of linear-sRGB
reflectance ``ρ`` (colour-science's reference data, :mod:`.charts`) then has radiance
``ρ ⊙ E · max(0, n·ω) / π``. With the camera's response already known, its linear
RGB ``c`` per patch gives, by least squares over the 24 patches,

    radiance ≈ M_full @ c,

factored for :class:`mifacerf.formats.capture.Radiometry` as ``exposure`` (camera
linear units per unit luminance) and ``colour_matrix = exposure * M_full``, which maps a
camera-neutral ``(1, 1, 1)`` to unit luminance.

Accuracy is reported as CIEDE2000 (``colour.delta_E(..., method="CIE 2000")``) between
the corrected and the reference patches in CIELAB (D65), both normalised to the
radiance of a perfect white under the same light.
"""
from __future__ import annotations

import numpy as np

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])


def fit_colour_matrix(camera_linear: np.ndarray, target: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Least-squares ``M`` (3, 3) with ``target ≈ camera_linear @ M.T``; inputs (P, 3)."""
    c = np.asarray(camera_linear, np.float64)
    t = np.asarray(target, np.float64)
    ok = np.all(np.isfinite(c), axis=1) & np.all(np.isfinite(t), axis=1)
    if ok.sum() < 3:
        raise ValueError(f"only {ok.sum()} valid patches; a colour matrix needs at least 3")
    w = np.ones(len(c)) if weights is None else np.asarray(weights, np.float64)
    sw = np.sqrt(w[ok])[:, None]
    M, *_ = np.linalg.lstsq(c[ok] * sw, t[ok] * sw, rcond=None)
    return M.T


def factor_exposure(M_full: np.ndarray) -> tuple[float, np.ndarray]:
    """Split ``M_full`` into (exposure, colour_matrix) with ``M_full = colour_matrix / exposure``
    and ``LUMINANCE @ colour_matrix @ (1, 1, 1) = 1``."""
    gain = float(LUMINANCE @ M_full @ np.ones(3))
    if not np.isfinite(gain) or gain <= 0:
        raise ValueError("the colour fit maps camera neutral to a non-positive luminance")
    exposure = 1.0 / gain
    return exposure, M_full * exposure


def lab_of(reflectance_rgb: np.ndarray) -> np.ndarray:
    """Linear sRGB reflectances (relative to a perfect white) -> CIELAB under D65."""
    import colour

    xyz = colour.RGB_to_XYZ(np.asarray(reflectance_rgb, np.float64), "sRGB")
    return colour.XYZ_to_Lab(xyz, colour.RGB_COLOURSPACES["sRGB"].whitepoint)


def delta_e2000(estimated_rgb: np.ndarray, reference_rgb: np.ndarray) -> np.ndarray:
    """CIEDE2000 per patch between two sets of linear sRGB reflectances (P, 3)."""
    import colour

    return np.asarray(colour.delta_E(lab_of(estimated_rgb), lab_of(reference_rgb), method="CIE 2000"))
