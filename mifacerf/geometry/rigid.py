"""Rigid transforms of 3-D points as 4 × 4 homogeneous matrices.

A transform ``T`` (4, 4) maps a world point ``p`` (3,) to ``T[:3, :3] @ p + T[:3, 3]``; rotations
are proper (det +1). Points are (N, 3) rows in metres; results are float64. The fits use Horn's
closed form (:mod:`.horn1987`).
"""
from __future__ import annotations

import numpy as np

from .horn1987 import horn


def homogeneous(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The transform (4, 4) of rotation ``R`` (3, 3) followed by translation ``t`` (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def apply(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Points ``P`` (N, 3) (any float dtype) moved by ``T`` (4, 4): (N, 3) float64."""
    return np.asarray(P, np.float64) @ T[:3, :3].T + T[:3, 3]


def rotation_angle_deg(R: np.ndarray) -> float:
    """The angle (degrees) of the rotation (3, 3) ``R``."""
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def rigid_from_points(P_from: np.ndarray, P_to: np.ndarray) -> np.ndarray:
    """The rigid transform (4, 4) that best maps ``P_from`` (N ≥ 3, 3) onto ``P_to`` (N, 3) (least squares)."""
    R, t = horn(np.asarray(P_from, np.float64), np.asarray(P_to, np.float64))
    return homogeneous(R, t)


def robust_rigid(P_from: np.ndarray, P_to: np.ndarray, keep: float = 0.35, iterations: int = 6) -> np.ndarray:
    """A rigid fit (4, 4) of ``P_from`` (N, 3) onto ``P_to`` (N, 3) using the most rigidly moving ``keep``
    fraction of the points (iteratively trimmed; rows with a non-finite coordinate are ignored)."""
    P, Q = np.asarray(P_from, np.float64), np.asarray(P_to, np.float64)
    m = np.isfinite(P).all(1) & np.isfinite(Q).all(1)
    P, Q = P[m], Q[m]
    sel = np.arange(len(P))
    T = rigid_from_points(P, Q)
    for _ in range(iterations):
        r = np.linalg.norm(apply(T, P) - Q, axis=1)
        n = max(3, int(keep * len(P)))
        sel = np.argsort(r)[:n]
        T = rigid_from_points(P[sel], Q[sel])
    return T
