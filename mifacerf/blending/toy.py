"""Analytic toy subjects for the blending tests and the benchmark.

A curved rectangular sheet (a stand-in for a face: ``nx × ny`` vertices, about
``size`` metres across) deformed by smooth, localised blendshapes (Gaussian
bumps of a few millimetres) and posed by random rigid head motions.  Any
parameter vector gives a mesh, so targets can be random blends of the sources'
parameters or parameter vectors outside the sources' set.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = ["grid_mesh", "ToySubject", "toy_subject"]


def grid_mesh(nx: int, ny: int, size: float = 0.16, curvature: float = 4.0):
    """Vertices ``(nx*ny, 3)`` (metres, +Z towards the viewer) and triangles ``(2(nx-1)(ny-1), 3)``."""
    x, y = np.meshgrid(np.linspace(-size / 2, size / 2, nx), np.linspace(-size / 2, size / 2, ny))
    z = -curvature * (x ** 2 + 0.5 * y ** 2)
    V = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    i, j = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    a = (j * nx + i).ravel()
    tri = np.concatenate([np.stack([a, a + 1, a + nx + 1], 1), np.stack([a, a + nx + 1, a + nx], 1)])
    return V, tri.astype(np.int64)


@dataclass
class ToySubject:
    """A toy subject: ``neutral`` ``(V, 3)``, ``triangles``, ``shapes`` ``(n_shapes, V, 3)``, ``regions``."""

    neutral: np.ndarray
    triangles: np.ndarray
    shapes: np.ndarray
    regions: dict

    def pose(self, params, rotvec=None, translation=None) -> np.ndarray:
        """Meshes ``(N, V, 3)`` for parameters ``(N, n_shapes)`` and optional rigid motions ``(N, 3)``."""
        params = np.atleast_2d(np.asarray(params, dtype=np.float64))
        X = self.neutral + np.einsum("ns,svc->nvc", params, self.shapes)
        # a little nonlinearity (skin sliding): displacement squared along the normal direction
        X[..., 2] += 8.0 * np.einsum("ns,svc->nvc", params, self.shapes)[..., 1] ** 2
        if rotvec is not None:
            R = Rotation.from_rotvec(np.atleast_2d(rotvec)).as_matrix()
            X = np.einsum("nab,nvb->nva", R, X)
        if translation is not None:
            X = X + np.atleast_2d(translation)[:, None, :]
        return X


def toy_subject(nx: int = 12, ny: int = 10, n_shapes: int = 6, seed: int = 0, amplitude: float = 6e-3,
                radius: float = 0.035) -> ToySubject:
    """A sheet with ``n_shapes`` Gaussian-bump blendshapes and four regions (quadrant-like bands)."""
    rng = np.random.default_rng(seed)
    V, F = grid_mesh(nx, ny)
    span = np.ptp(V[:, :2], axis=0)
    shapes = []
    for _ in range(n_shapes):
        c = V[:, :2].min(0) + rng.random(2) * span
        d = rng.normal(size=3)
        d /= np.linalg.norm(d)
        g = np.exp(-np.sum((V[:, :2] - c) ** 2, axis=1) / (2 * radius ** 2))
        shapes.append(amplitude * g[:, None] * d[None, :])
    x, y = V[:, 0], V[:, 1]
    regions = {
        "forehead": np.nonzero(y > 0.03)[0],
        "cheek_left": np.nonzero((x > 0) & (y <= 0.035) & (y > -0.03))[0],
        "cheek_right": np.nonzero((x <= 0) & (y <= 0.035) & (y > -0.03))[0],
        "mouth": np.nonzero(y <= -0.025)[0],
    }
    return ToySubject(neutral=V, triangles=F, shapes=np.array(shapes), regions=regions)


def random_sources(subject: ToySubject, n_sources: int, seed: int = 1, max_active: int = 3,
                   max_angle: float = 0.15, max_shift: float = 0.02):
    """Sources ``(n, V, 3)`` (source 0 is the neutral, unposed) and their parameters ``(n, n_shapes)``.

    Each other source activates 1..``max_active`` blendshapes with weights in (0, 1] and has a random
    rigid pose.
    """
    rng = np.random.default_rng(seed)
    S = subject.shapes.shape[0]
    params = np.zeros((n_sources, S))
    for i in range(1, n_sources):
        k = rng.integers(1, max_active + 1)
        act = rng.choice(S, size=min(k, S), replace=False)
        params[i, act] = rng.uniform(0.2, 1.0, size=act.size)
    rot = rng.normal(size=(n_sources, 3)) * max_angle / 2
    sh = rng.normal(size=(n_sources, 3)) * max_shift / 2
    rot[0] = 0
    sh[0] = 0
    return subject.pose(params, rot, sh), params
