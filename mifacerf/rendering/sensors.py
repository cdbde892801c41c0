"""Mitsuba perspective sensors ↔ mifacerf cameras (OpenCV conventions).

Mitsuba's camera frame has +x left, +y up, +z forward; OpenCV's +x right, +y down,
+z forward, so ``R_cv = diag(−1, −1, 1) · R_mitsubaᵀ``. Mitsuba's image plane spans
``[0, W] × [0, H]`` with pixel centres at half-integers; ours puts centres at integers,
so the principal point of a centred Mitsuba camera is ``((W−1)/2, (H−1)/2)``; Mitsuba's
``principal_point_offset_{x,y}`` shift it by minus that fraction of the image size. Mitsuba's
pinhole has no lens distortion: a mifacerf camera with distortion has no exact
Mitsuba sensor (:func:`sensor_dict` refuses it).
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..variant import ensure_variant

FLIP = np.diag([-1.0, -1.0, 1.0])


def camera_from_sensor(sensor, name: str = "sensor") -> Camera:
    """A :class:`Camera` equivalent to a Mitsuba ``perspective`` sensor."""
    mi = ensure_variant()
    params = mi.traverse(sensor)
    film = sensor.film()
    w, h = (int(v) for v in film.crop_size())
    M = np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    Rm, tm = M[:3, :3], M[:3, 3]
    scale = np.linalg.norm(Rm, axis=0)
    Rm = Rm / scale
    x_fov = float(np.asarray(params["x_fov"]).ravel()[0]) if "x_fov" in params else None
    if x_fov is None:
        raise ValueError("only Mitsuba 'perspective' sensors can be converted to cameras")
    fx = (w / 2) / np.tan(np.radians(x_fov) / 2)
    off_x = float(np.asarray(params["principal_point_offset_x"]).ravel()[0]) if "principal_point_offset_x" in params else 0.0
    off_y = float(np.asarray(params["principal_point_offset_y"]).ravel()[0]) if "principal_point_offset_y" in params else 0.0
    K = np.array([[fx, 0, (w - 1) / 2 - off_x * w], [0, fx, (h - 1) / 2 - off_y * h], [0, 0, 1]])
    R = FLIP @ Rm.T
    t = -R @ tm
    return Camera(name, w, h, K, np.zeros(5), R, t)


def sensor_dict(camera: Camera, spp: int = 4, alpha: bool = True) -> dict:
    """A Mitsuba ``perspective`` sensor dict for a distortion-free camera with square pixels."""
    mi = ensure_variant()
    if np.any(np.abs(camera.dist) > 0):
        raise ValueError(f"camera {camera.name!r} has lens distortion, which Mitsuba's perspective sensor lacks")
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    if abs(fx - fy) > 1e-6 * fx:
        raise ValueError(f"camera {camera.name!r} has non-square pixels")
    w, h = camera.width, camera.height
    Rm = (FLIP @ camera.R).T
    M = np.eye(4)
    M[:3, :3] = Rm
    M[:3, 3] = camera.centre
    return {
        "type": "perspective",
        "fov": float(np.degrees(2 * np.arctan((w / 2) / fx))),
        "fov_axis": "x",
        # Mitsuba's offsets move the principal point the other way (fractions of the image size)
        "principal_point_offset_x": float(((w - 1) / 2 - camera.K[0, 2]) / w),
        "principal_point_offset_y": float(((h - 1) / 2 - camera.K[1, 2]) / h),
        "to_world": mi.ScalarTransform4f(M),
        "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"},
                 "pixel_format": "rgba" if alpha else "rgb"},
        "sampler": {"type": "stratified", "sample_count": spp},
    }
