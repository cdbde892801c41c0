"""Texture coordinates (paper §4, §6): where every template vertex lies in every camera's reflectance field.

For an expression's registered mesh: ``uv`` (C, T, 2) the projection of every vertex into
every camera (pixels, OpenCV convention, lens distortion included) and ``visible`` (C, T)
whether the vertex is seen there — in the image, facing the camera and not occluded by
the expression's own mesh (ray-traced with Mitsuba, :class:`.visibility.Visibility`).
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..geometry.visibility import Visibility


def texture_coordinates(V: np.ndarray, cams: list[Camera], vis: Visibility) -> tuple[np.ndarray, np.ndarray]:
    """(uv (C, T, 2) float32, visible (C, T) bool) of the mesh ``V`` (T, 3)."""
    uv = np.stack([cam.project(V)[0] for cam in cams]).astype(np.float32)
    visible = vis(V, cams, min_cos=0.0)
    visible &= np.isfinite(uv).all(-1)
    uv = np.nan_to_num(uv, nan=-1.0)
    return uv, visible
