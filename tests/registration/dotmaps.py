"""Synthetic dot-strength maps for the snap tests: a Gaussian blob per point, and a curved grid of points
seen by the six-camera ring."""
import numpy as np

from mifacerf.geometry.triangulate import project_all
from mifacerf.rig import CAMERA_LAYOUTS, camera_ring


def strength_maps(cams, X, seen=None, sigma=0.9, size=128, weights=None):
    """(C,) float32 (size, size) maps: a Gaussian blob (peak ``weights[k]`` or 1) at each point ``X`` (N, 3)
    in the views where ``seen`` (C, N) says it shows (default: wherever it projects)."""
    yy, xx = np.mgrid[0:size, 0:size]
    uv = project_all(cams, X)
    out = []
    for c in range(len(cams)):
        m = np.zeros((size, size))
        for k in range(len(X)):
            u, v = uv[c, k]
            if (seen is not None and not seen[c, k]) or not np.isfinite(u):
                continue
            w = 1.0 if weights is None else weights[k]
            m = np.maximum(m, w * np.exp(-((xx - u) ** 2 + (yy - v) ** 2) / (2 * sigma ** 2)))
        out.append(m.astype(np.float32))
    return out


def dot_grid():
    """(cameras, X): the 128 px six-camera ring and 56 points (world, metres) on a paraboloid facing it."""
    cams = camera_ring(CAMERA_LAYOUTS[6], width=128, height=128, seed=2)
    g = np.stack(np.meshgrid(np.linspace(-0.05, 0.05, 7), np.linspace(-0.06, 0.06, 8)), -1).reshape(-1, 2)
    X = np.stack([g[:, 0], g[:, 1], 0.09 - 3 * (g[:, 0] ** 2 + g[:, 1] ** 2)], 1)
    return cams, X
