"""3 × 3 local maxima of a 2-D map (dot-strength maps of registration and tracking).

Maps are (H, W) arrays indexed ``[v, u]`` (row = image y, column = image x, pixel centres at
integer positions, OpenCV convention). A pixel is a local maximum when it is not smaller than
any of its up to 8 neighbours inside the image (plateaus give several maxima); the comparison
is made in the map's own dtype. NaN pixels are never maxima and do not hide a neighbour
(they count as -inf).
"""
from __future__ import annotations

import numpy as np


def local_maxima(strength: np.ndarray, threshold: float, *, positive: bool = False) -> np.ndarray:
    """(H, W) bool: the 3 × 3 local maxima of ``strength`` (H, W) that are at least ``threshold``
    (and, with ``positive``, also strictly above zero)."""
    import cv2

    S = np.asarray(strength)
    if S.ndim != 2:
        raise ValueError(f"local_maxima: expected an (H, W) map, got shape {S.shape}")
    D = np.where(np.isnan(S), -np.inf, S).astype(S.dtype, copy=False)
    out = (S >= cv2.dilate(np.ascontiguousarray(D), np.ones((3, 3), np.uint8))) & (S >= threshold)
    if positive:
        out &= S > 0
    return out


def maxima_points(strength: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """The :func:`local_maxima` of ``strength`` (H, W) at or above ``threshold`` as pixel positions
    (M, 2) float64 ``(u, v)`` in row-major order, and their values (M,) in the map's dtype."""
    S = np.asarray(strength)
    v, u = np.nonzero(local_maxima(S, threshold))
    return np.stack([u, v], 1).astype(np.float64), S[v, u]
