"""Interpolation between the light stage's directions, for arbitrary light directions.

The light directions are triangulated on the sphere (their convex hull, scipy /
qhull: the spherical Delaunay triangulation). A direction ω inside triangle
(a, b, c) gets the weights λ solving ``λ_a d_a + λ_b d_b + λ_c d_c ∝ ω`` (gnomonic
barycentrics), normalised to sum to 1 — exact at the captured directions (one-hot),
continuous across edges, non-negative.

Point location uses a lat-long lookup grid storing, per cell, the triangle that
contains the cell's centre; at run time the cell's triangle is tried first and, if ω
lies outside it (near an edge), its clamped weights are used — the error is confined
to a sliver of one grid cell along the edges. Degenerate layouts (fewer than four
lights, or all on one great circle) fall back to the nearest light.

Two rules, named as the exact path's light bases (:data:`mifacerf.environment.LIGHT_BASIS_METHODS`), so that
the material and the exact path agree under the same name: ``hat`` (this class's default) is the interpolation
above (the hat basis: each direction shared by the three lights of its triangle); ``voronoi`` (the
material's default, as the exact path's) gives each direction wholly to its nearest light (the spherical-Voronoi cell the exact path
integrates the environment over). Under ``voronoi`` the material integrates an environment exactly as the
exact path does (∫ E(ω) F[nearest(ω)] dω = Σ_l F[l] ∫_cell(l) E); a point light moving across the face
changes the shading in steps at the cell edges. Its point location: per lookup-grid cell the lights nearest
to the cell's centre, corners and edge midpoints (at most four), of which the kernel takes the nearest.
"""
from __future__ import annotations

import numpy as np

from ..environment import direction_to_uv, latlong_grid
from ..jitarrays import to_jit
from ..variant import ensure_variant


class LightInterpolator:
    """``directions`` (L, 3) unit world vectors towards the lights; ``grid_height`` rows of the lookup grid."""

    def __init__(self, directions: np.ndarray, grid_height: int = 128, method: str = "hat"):
        from scipy.spatial import ConvexHull, QhullError

        from ..environment import LIGHT_BASIS_METHODS
        from ..methods import lookup

        lookup(LIGHT_BASIS_METHODS, method, "light basis")
        self.method = method
        self.directions = np.asarray(directions, np.float64)
        self.n = len(self.directions)
        self.grid_h, self.grid_w = grid_height, 2 * grid_height
        self.nearest_only = True
        if self.n >= 4 and np.linalg.matrix_rank(self.directions, tol=1e-9) == 3:
            try:
                hull = ConvexHull(self.directions)
                tri = hull.simplices.copy()
                self.nearest_only = False
            except QhullError:
                pass
        if self.nearest_only:
            self.triangles = np.zeros((0, 3), np.int64)
            self.inverse = np.zeros((0, 3, 3))
            dirs, _ = latlong_grid(self.grid_h)
            self.grid = np.argmax(dirs.reshape(-1, 3) @ self.directions.T, axis=1)
            self.candidates = self._nearest_candidates()
            return
        self.triangles = tri
        M = np.stack([self.directions[tri[:, k]] for k in range(3)], axis=2)  # columns = corners
        self.inverse = np.linalg.inv(M)
        dirs, _ = latlong_grid(self.grid_h)
        self.grid = self._containing(dirs.reshape(-1, 3))
        self.candidates = self._nearest_candidates()

    def _containing(self, dirs: np.ndarray, chunk: int = 2048) -> np.ndarray:
        """(N,) for directions (N, 3): the triangle whose smallest gnomonic barycentric is largest (the one
        holding the direction; not the antipodal one, whose barycentrics sum ≤ 0). The three barycentrics
        are computed as three (n, M) arrays, a chunk of directions at a time: a reduction over an axis of
        3 and an (N, M, 3) einsum took 1-2 s for the 128-row grid and 380 triangles."""
        inv = self.inverse                                             # (M, 3, 3): λ = inv @ ω
        out = np.empty(len(dirs), np.int64)
        for a in range(0, len(dirs), chunk):
            d = dirs[a:a + chunk]
            lam = [d[:, 0:1] * inv[None, :, i, 0] + d[:, 1:2] * inv[None, :, i, 1] + d[:, 2:3] * inv[None, :, i, 2]
                   for i in range(3)]                                  # 3 × (n, M)
            score = np.minimum(np.minimum(lam[0], lam[1]), lam[2])
            score[(lam[0] + lam[1] + lam[2]) <= 0] = -np.inf           # the antipodal triangle
            out[a:a + chunk] = np.argmax(score, axis=1)
        return out

    def _nearest_candidates(self, n: int = 4) -> np.ndarray:
        """(cells, n) lights nearest to each grid cell's centre, corners and edge midpoints (repeated to n)."""
        from ..environment import uv_to_direction

        h, w = self.grid_h, self.grid_w
        yy, xx = np.mgrid[0:h, 0:w]
        out = []
        for dy in (0.0, 0.5, 1.0):
            for dx in (0.0, 0.5, 1.0):
                uv = np.stack([(xx + dx) / w, np.clip((yy + dy) / h, 1e-6, 1 - 1e-6)], -1).reshape(-1, 2)
                out.append(np.argmax(uv_to_direction(uv) @ self.directions.T, axis=1))
        near = np.stack(out, 1)   # (cells, 9)
        # per row: its distinct lights in order of first appearance, the first n of them, repeated cyclically
        # to n (vectorised; a Python loop over the 32,768 cells took 0.15 s)
        first = np.ones(near.shape, bool)
        for j in range(1, near.shape[1]):
            first[:, j] = (near[:, :j] != near[:, j:j + 1]).all(axis=1)
        count = np.minimum(first.sum(1), n)
        rank = np.cumsum(first, axis=1) - 1
        uniq = np.zeros((len(near), n), np.int64)
        rows, cols = np.nonzero(first & (rank < n))
        uniq[rows, rank[rows, cols]] = near[rows, cols]
        return uniq[np.arange(len(near))[:, None], np.arange(n)[None] % count[:, None]]

    def _cell(self, d: np.ndarray) -> np.ndarray:
        uv = direction_to_uv(d)
        x = np.minimum((uv[:, 0] * self.grid_w).astype(np.int64), self.grid_w - 1)
        y = np.minimum((uv[:, 1] * self.grid_h).astype(np.int64), self.grid_h - 1)
        return y * self.grid_w + x

    def weights(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) directions → light indices (N, 3) and weights (N, 3) (≥ 0, sum 1)."""
        d = np.asarray(directions, np.float64).reshape(-1, 3)
        d = d / np.linalg.norm(d, axis=1, keepdims=True)
        cell = self._cell(d)
        if self.method == "voronoi":
            idx = np.zeros((len(d), 3), np.int64)
            cand = self.candidates[cell]
            dots = np.einsum("nj,nkj->nk", d, self.directions[cand])
            idx[:, 0] = cand[np.arange(len(d)), np.argmax(dots, axis=1)]
            w = np.zeros((len(d), 3))
            w[:, 0] = 1.0
            return idx, w
        if self.nearest_only:
            idx = np.zeros((len(d), 3), np.int64)
            idx[:, 0] = np.argmax(d @ self.directions.T, axis=1)
            w = np.zeros((len(d), 3))
            w[:, 0] = 1.0
            return idx, w
        t = self.grid[cell]
        lam = np.clip(np.einsum("nij,nj->ni", self.inverse[t], d), 0.0, None)
        lam /= np.maximum(lam.sum(1, keepdims=True), 1e-300)
        return self.triangles[t], lam

    # ------------------------------------------------------------------ Dr.Jit
    def to_device(self):
        """Upload the tables (call once; :meth:`weights_jit` uses them)."""
        mi = ensure_variant()
        self._grid_dev = to_jit(mi.UInt32, self.grid.astype(np.uint32))
        self._tri_dev = to_jit(mi.UInt32, self.triangles.reshape(-1).astype(np.uint32) if len(self.triangles)
                               else np.zeros(3, np.uint32))
        self._inv_dev = to_jit(mi.Float, self.inverse.reshape(-1) if len(self.inverse) else np.zeros(9))
        self._cand_dev = to_jit(mi.UInt32, self.candidates.reshape(-1).astype(np.uint32))
        self._dirs_dev = to_jit(mi.Float, self.directions.reshape(-1))
        return self

    def direction_jit(self, ids, active=True):
        """Dr.Jit: the directions (Vector3f) of the lights ``ids`` (UInt32)."""
        import drjit as dr

        mi = ensure_variant()
        if not hasattr(self, "_dirs_dev"):
            self.to_device()
        return mi.Vector3f(*[dr.gather(mi.Float, self._dirs_dev, ids * 3 + j, active) for j in range(3)])

    def weights_jit(self, d, active=True):
        """Dr.Jit version: Vector3f world directions → ([UInt32]*3 light ids, [Float]*3 weights)."""
        import drjit as dr

        mi = ensure_variant()
        if not hasattr(self, "_grid_dev"):
            self.to_device()
        d = dr.normalize(d)
        u = dr.atan2(d.x, -d.z) * (1.0 / (2 * np.pi))
        u = u - dr.floor(u)
        v = dr.safe_acos(d.y) * (1.0 / np.pi)
        x = dr.minimum(mi.UInt32(u * self.grid_w), self.grid_w - 1)
        y = dr.minimum(mi.UInt32(v * self.grid_h), self.grid_h - 1)
        if self.method == "voronoi":
            cell = y * self.grid_w + x
            best, best_dot = mi.UInt32(0), mi.Float(-2.0)
            for k in range(self.candidates.shape[1]):
                c = dr.gather(mi.UInt32, self._cand_dev, cell * self.candidates.shape[1] + k, active)
                dot = sum(dr.gather(mi.Float, self._dirs_dev, c * 3 + j, active) * d[j] for j in range(3))
                better = dot > best_dot
                best = dr.select(better, c, best)
                best_dot = dr.select(better, dot, best_dot)
            zero = dr.zeros(mi.UInt32, dr.width(best))
            return [best, zero, zero], [dr.full(mi.Float, 1.0, dr.width(best)), mi.Float(0), mi.Float(0)]
        t = dr.gather(mi.UInt32, self._grid_dev, y * self.grid_w + x, active)
        if self.nearest_only:
            zero = dr.zeros(mi.UInt32, dr.width(t))
            return [t, zero, zero], [dr.full(mi.Float, 1.0, dr.width(t)), mi.Float(0), mi.Float(0)]
        ids = [dr.gather(mi.UInt32, self._tri_dev, t * 3 + k, active) for k in range(3)]
        lam = []
        for i in range(3):
            row = [dr.gather(mi.Float, self._inv_dev, t * 9 + i * 3 + j, active) for j in range(3)]
            lam.append(dr.maximum(row[0] * d.x + row[1] * d.y + row[2] * d.z, 0.0))
        inv = dr.rcp(dr.maximum(lam[0] + lam[1] + lam[2], 1e-30))
        return ids, [l_ * inv for l_ in lam]
