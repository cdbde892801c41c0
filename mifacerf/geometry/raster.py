"""Primary hits of a camera's samples by rasterisation (Numba), instead of a ray cast through Mitsuba.

A render's camera rays all start at the camera's centre, so the triangle a ray meets first is the one
whose projection holds the ray's point on the image plane, nearest in depth: a z-buffer over the
camera's samples. :func:`camera_hits` projects every triangle onto the undistorted image plane z = 1
(camera coordinates), tests the samples of the grid cells its box covers (Möller–Trumbore in float64,
edges inclusive, so that a sample on an edge shared by two triangles is in both and none falls between
them) and keeps the nearest front hit. The answer is the ray cast's — the same triangle and
barycentrics for every sample up to rounding (tested against Mitsuba's ``ray_intersect_preliminary``,
tests/test_raster.py) — with two documented differences: every back face is passed through (Mitsuba's
culled trace stops after :attr:`.meshscene.MeshScene.trace`'s ``max_layers`` = 4 of them), and a
triangle that reaches behind the camera's plane (z ≤ :data:`NEAR`) cannot be projected: the caller then
ray-casts (:meth:`.meshscene.MeshScene.camera_hits` does).

Why (docs/rendering.md, "Seventh pass"): the renderer moves its mesh every frame, and Mitsuba/Embree
rebuild the whole acceleration structure on each update (no refit can be asked for from Python): 25–30 ms
of a 256² frame for the 17.6k triangles of the demo model's traced head, beside 20 ms of ray casts. This
needs no acceleration structure; the Mitsuba scene is then updated only when something else casts
rays into it (the eyes' and teeth's shadow rays). Used on the CPU variants (``llvm_*``); the CUDA variants
ray-cast on the device. ``MIFACERF_NUMBA_RASTER=0`` ray-casts everywhere.

Units: camera coordinates in metres (x right, y down, z forward: :class:`mifacerf.camera.Camera`).
"""
from __future__ import annotations

import numpy as np

#: the nearest depth (metres) a projected vertex may have; a triangle with a vertex nearer is not rasterised
NEAR = 1e-6


class SampleGrid:
    """A camera's samples on the image plane, binned once: ``plane`` (N, 2) float64 the rays' (x, y) at
    z = 1, ``order`` (N,) int64 the samples sorted by cell, ``starts`` (cells + 1,) int64 each cell's first,
    ``grid`` (5,) float64 (x0, y0, 1 / cell, columns, rows), ``norm`` (N,) float64 |(x, y, 1)| (a depth z
    is the distance z · norm along the unit ray)."""

    def __init__(self, plane: np.ndarray, cells_x: int, cells_y: int):
        plane = np.ascontiguousarray(plane, np.float64)
        if plane.ndim != 2 or plane.shape[1] != 2 or not len(plane):
            raise ValueError(f"sample plane of shape {plane.shape}: expected (N, 2), N > 0")
        if not np.isfinite(plane).all():
            raise ValueError("sample plane has NaN/Inf positions")
        lo, hi = plane.min(0), plane.max(0)
        cell = max(float((hi[0] - lo[0]) / max(cells_x, 1)), float((hi[1] - lo[1]) / max(cells_y, 1)), 1e-12)
        gw = int((hi[0] - lo[0]) / cell) + 1
        gh = int((hi[1] - lo[1]) / cell) + 1
        ij = np.minimum(((plane - lo) / cell).astype(np.int64), [gw - 1, gh - 1])
        key = ij[:, 1] * gw + ij[:, 0]
        self.plane = plane
        self.order = np.argsort(key, kind="stable").astype(np.int64)
        self.starts = np.searchsorted(key[self.order], np.arange(gw * gh + 1)).astype(np.int64)
        self.grid = np.array([lo[0], lo[1], 1.0 / cell, gw, gh], np.float64)
        self.norm = np.sqrt(1.0 + (plane ** 2).sum(1))


def available() -> bool:
    """Whether Numba is importable (the kernel's only need); ``MIFACERF_NUMBA_RASTER=0`` switches it off."""
    from ..formats.files import switched_off

    if switched_off("MIFACERF_NUMBA_RASTER"):
        return False
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def camera_hits(vertices: np.ndarray, faces: np.ndarray, centre: np.ndarray, R: np.ndarray, samples: SampleGrid,
                cull_back: bool = True, tessellation=None):
    """The nearest hits of a camera's samples on a mesh, or None where a triangle reaches behind the
    camera (z ≤ :data:`NEAR`; ray-cast those frames).

    ``vertices`` (V, 3) world, ``faces`` (F, 3); the camera's centre (3,) and rotation ``R`` (3, 3)
    (world → camera: p_cam = R (p − centre)); ``samples`` its :class:`SampleGrid`; ``tessellation``: the
    :class:`.boubekeur2008.PhongTessellation` whose sub-faces ``faces`` are, to report hits on its coarse
    faces. Returns (tri (N,) int64, −1 where nothing is hit; the rasterised face (N,) (= tri without a
    tessellation); bary (N, 3) (b0, b1, b2) of tri's corners; t (N,) distance along the unit ray, inf
    where nothing is hit)."""
    from ..hostpool import run_all, threads
    from ._numba_raster import finish_rows, raster_rows

    faces = np.ascontiguousarray(faces, np.int64)
    P = np.ascontiguousarray((np.asarray(vertices, np.float64) - np.asarray(centre, np.float64)) @ np.asarray(R).T)
    kept = np.zeros(0, np.int64)
    behind = P[faces, 2] <= NEAR if faces.size else np.zeros((0, 3), bool)
    if behind.any():
        whole = behind.all(1)
        if (behind.any(1) & ~whole).any():
            return None               # a triangle through the camera's plane: its projection is not one
        kept = np.flatnonzero(~whole)  # wholly behind the camera: no ray from it meets them
        faces = np.ascontiguousarray(faces[kept])
    n = len(samples.plane)
    best = np.full(n, np.inf)
    hit = np.full(n, -1, np.int64)
    u = np.empty(n)
    v = np.empty(n)
    gh = int(samples.grid[4])
    k = max(1, min(threads(), gh))
    cuts = [gh * b // k for b in range(k + 1)]     # one band of grid rows per thread: disjoint samples
    run_all([lambda lo=lo, hi=hi: raster_rows(P, faces, samples.plane, samples.order, samples.starts, samples.grid,
                                              bool(cull_back), best, hit, u, v, lo, hi)
             for lo, hi in zip(cuts[:-1], cuts[1:])])
    if tessellation is None:
        parent, corners = np.zeros(0, np.int64), np.zeros((0, 3, 3))
    else:
        parent, corners = tessellation.parent, tessellation.corner_bary
    tri, sub, bary, t = np.empty(n, np.int64), np.empty(n, np.int64), np.empty((n, 3)), np.empty(n)
    finish_rows(best, hit, u, v, samples.norm, kept, np.ascontiguousarray(parent, np.int64),
                np.ascontiguousarray(corners, np.float64), tri, sub, bary, t)
    return tri, sub, bary, t
