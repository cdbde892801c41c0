"""Dr.Jit geometry shared by the shading kernels (frame, material, parts).

Cameras are rows of a flat parameter table, :data:`CAM_PARAMS` floats each
(:func:`camera_params`): R (9, row-major), t (3), fx, fy, cx, cy, k1, k2, p1, p2, k3, width,
height — the OpenCV model of :mod:`mifacerf.camera`.
"""
from __future__ import annotations

import numpy as np

from ..variant import ensure_variant

CAM_PARAMS = 24  # R (9), t (3), fx, fy, cx, cy, k1, k2, p1, p2, k3, width, height, pad


def camera_params(cam) -> np.ndarray:
    """One camera's row of the parameter table, (CAM_PARAMS,)."""
    p = np.zeros(CAM_PARAMS)
    p[0:9] = cam.R.reshape(-1)
    p[9:12] = cam.t
    p[12:16] = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    p[16:21] = cam.dist[:5]
    p[21:23] = cam.width, cam.height
    return p


def project(P, point):
    """Project world points through a camera whose parameters ``P(e)`` returns (a gather from the table).

    ``point``: three Floats (x, y, z). Returns (u, v, distance from the camera centre, z_camera,
    width, height) as Dr.Jit values (u, v in OpenCV pixel coordinates, lens distortion included).
    """
    import drjit as dr

    mi = ensure_variant()
    pc = [P(3 * r) * point[0] + P(3 * r + 1) * point[1] + P(3 * r + 2) * point[2] + P(9 + r) for r in range(3)]
    iz = dr.rcp(pc[2])
    x, y = pc[0] * iz, pc[1] * iz
    k1, k2, p1, p2, k3 = P(16), P(17), P(18), P(19), P(20)
    r2 = x * x + y * y
    rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    dist = dr.norm(mi.Vector3f(pc[0], pc[1], pc[2]))
    return P(12) * xd + P(14), P(13) * yd + P(15), dist, pc[2], mi.Int32(P(21)), mi.Int32(P(22))


def bilinear_taps(u, v, width, height, active):
    """The 2x2 texels around (u, v): a list of (flat pixel index (UInt32), weight, inside) per tap."""
    import drjit as dr

    mi = ensure_variant()
    x0f, y0f = dr.floor(u), dr.floor(v)
    fx, fy = u - x0f, v - y0f
    x0, y0 = mi.Int32(x0f), mi.Int32(y0f)
    taps = []
    for dy in (0, 1):
        for dx in (0, 1):
            xx, yy = x0 + dx, y0 + dy
            inside = active & (xx >= 0) & (yy >= 0) & (xx < width) & (yy < height)
            pix = mi.UInt32(dr.select(inside, yy * width + xx, 0))
            w = dr.select(inside, (fx if dx else 1 - fx) * (fy if dy else 1 - fy), 0.0)
            taps.append((pix, w, inside))
    return taps


def barycentric(triangles, vertices, tri, p):
    """Barycentrics [b0, b1, b2] of world points ``p`` (Point3f) in triangles ``tri`` (UInt32), with the
    mesh given as flat device arrays ``triangles`` (UInt32, 3 per face) and ``vertices`` (Float, 3 per vertex)."""
    import drjit as dr

    mi = ensure_variant()
    v = []
    for k in range(3):
        i = dr.gather(mi.UInt32, triangles, tri * 3 + k)
        v.append(mi.Point3f(*[dr.gather(mi.Float, vertices, i * 3 + d) for d in range(3)]))
    e0, e1, d = v[1] - v[0], v[2] - v[0], p - v[0]
    d00, d01, d11 = dr.dot(e0, e0), dr.dot(e0, e1), dr.dot(e1, e1)
    d20, d21 = dr.dot(d, e0), dr.dot(d, e1)
    inv = dr.rcp(dr.maximum(d00 * d11 - d01 * d01, 1e-30))
    b1 = (d11 * d20 - d01 * d21) * inv
    b2 = (d00 * d21 - d01 * d20) * inv
    return [1 - b1 - b2, b1, b2]
