"""Per-vertex visibility of a template mesh from the cameras, ray-traced with Mitsuba.

A vertex is visible from a camera when it projects inside the image, the segment to the
camera centre does not hit the mesh (:meth:`.meshscene.MeshScene.visible_from`), and the surface
faces the camera by more than ``min_cos`` (the cosine between the vertex normal and the
direction to the camera): dots seen at grazing angles are foreshortened into streaks and
left out of the dot strength.
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (T, 3); zero for vertices in no triangle."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64).reshape(-1, 3)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    out = np.zeros_like(V)
    for k in range(3):
        np.add.at(out, F[:, k], n)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(norm > 0, out / np.maximum(norm, 1e-300), 0.0)


class Visibility:
    """Ray-traced visibility against a template mesh whose vertices change per expression."""

    def __init__(self, triangles: np.ndarray, n_vertices: int, tol: float = 1e-3):
        self.F = np.asarray(triangles, np.int64).reshape(-1, 3)
        self.n = n_vertices
        self.tol = tol
        self._scene = None

    def scene(self, V: np.ndarray):
        from ..geometry.meshscene import MeshScene

        if self._scene is None:
            self._scene = MeshScene(V, self.F)
        else:
            self._scene.set_vertices(V)
        return self._scene

    def __call__(self, V: np.ndarray, cams: list[Camera], points: np.ndarray | None = None,
                 normals: np.ndarray | None = None, min_cos: float = 0.2, return_cos: bool = False):
        """(C, N) visibility of ``points`` (default: the mesh vertices ``V``) on the mesh ``V``
        (and, with ``return_cos``, the (C, N) cosines between the normal and the view direction)."""
        V = np.asarray(V, np.float64)
        P = V if points is None else np.asarray(points, np.float64)
        N = vertex_normals(V, self.F) if normals is None and points is None else normals
        scene = self.scene(V)
        out = np.zeros((len(cams), len(P)), bool)
        cos = np.full((len(cams), len(P)), np.nan)
        for c, cam in enumerate(cams):
            vis = scene.visible_from(P, cam, tol=self.tol)
            if N is not None:
                d = cam.centre - P
                d /= np.linalg.norm(d, axis=1, keepdims=True)
                cosv = np.einsum("ij,ij->i", d, N)
                cos[c] = np.where(np.linalg.norm(N, axis=1) > 0, cosv, np.nan)
                if min_cos is not None:
                    vis &= (cosv > min_cos) | (np.linalg.norm(N, axis=1) == 0)
            out[c] = vis
        return (out, cos) if return_cos else out
