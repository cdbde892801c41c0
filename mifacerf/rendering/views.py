"""View sampling over the capture cameras (paper §6.1).

Each capture camera is represented by its **inverse look vector** (the unit vector
from the subject towards the camera, world frame, = −optical axis) in polar
coordinates ``(yaw, pitch)``: ``yaw = atan2(x, z)`` (about +Y, from +Z towards +X)
and ``pitch = asin(y)``, radians — a chart centred on the front of the face, where
the cameras are. The cameras are Delaunay-triangulated in that chart (scipy). A
novel view direction (already rotated into the source expression's local pose by
``R_ts``) is located in the triangulation and gets the barycentric weights of its
triangle's 1–3 cameras.

Outside the cameras' convex hull (documented, continuous fall-back): the view is
replaced by the nearest point of the hull's boundary in the chart, whose weights
are those of that boundary edge (2 cameras) or vertex (1 camera). Degenerate
layouts: one camera → weight 1; cameras on a line in the chart → 1-D linear
interpolation along it (clamped at the ends).
"""
from __future__ import annotations

import numpy as np


def to_chart(directions: np.ndarray) -> np.ndarray:
    """(..., 3) unit world directions → (..., 2) (yaw, pitch) in radians."""
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return np.stack([np.arctan2(d[..., 0], d[..., 2]), np.arcsin(np.clip(d[..., 1], -1, 1))], axis=-1)


def _segment_closest(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points of segments a→b to points p: returns (t in [0,1] (N, E), squared distance (N, E))."""
    ab = b - a  # (E, 2)
    denom = np.maximum((ab * ab).sum(-1), 1e-300)
    t = np.clip(((p[:, None, :] - a[None]) * ab[None]).sum(-1) / denom, 0.0, 1.0)
    q = a[None] + t[..., None] * ab[None]
    return t, ((p[:, None, :] - q) ** 2).sum(-1)


class ViewSampler:
    """Camera weights for view directions. ``camera_dirs`` (C, 3): inverse look vectors (world)."""

    def __init__(self, camera_dirs: np.ndarray):
        from scipy.spatial import Delaunay, QhullError

        self.points = to_chart(np.asarray(camera_dirs, np.float64).reshape(-1, 2 + 1))
        self.n = len(self.points)
        if self.n == 0:
            raise ValueError("view sampling needs at least one camera")
        self.kind = "single" if self.n == 1 else "delaunay"
        self.tri = None
        if self.n >= 3:
            try:
                self.tri = Delaunay(self.points)
            except QhullError:
                self.kind = "line"
        elif self.n == 2:
            self.kind = "line"
        if self.kind == "line":
            centred = self.points - self.points.mean(0)
            axis = np.linalg.svd(centred, full_matrices=False)[2][0]
            self.line_axis = axis
            self.line_order = np.argsort(centred @ axis)
            self.line_pos = (centred @ axis)[self.line_order]
            self.line_origin = self.points.mean(0)
        if self.tri is not None:
            hull = self.tri.convex_hull  # (E, 2) boundary edges
            self.hull_edges = hull
            self.hull_a = self.points[hull[:, 0]]
            self.hull_b = self.points[hull[:, 1]]

    @classmethod
    def from_cameras(cls, cameras) -> "ViewSampler":
        """From :class:`mifacerf.camera.Camera` objects: inverse look vector = −(optical axis)."""
        return cls(np.stack([-c.forward for c in cameras]))

    def weights(self, view_dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Camera weights for (N, 3) view directions → (indices (N, 3) int, weights (N, 3) float).

        Weights are ≥ 0 and sum to 1; unused slots have weight 0 (index 0).
        """
        p = to_chart(np.asarray(view_dirs, np.float64).reshape(-1, 3))
        n = len(p)
        idx = np.zeros((n, 3), np.int64)
        w = np.zeros((n, 3))
        if self.kind == "single":
            w[:, 0] = 1.0
            return idx, w
        if self.kind == "line":
            s = (p - self.line_origin) @ self.line_axis
            pos = self.line_pos
            k = np.clip(np.searchsorted(pos, s) - 1, 0, len(pos) - 2)
            span = np.maximum(pos[k + 1] - pos[k], 1e-300)
            t = np.clip((s - pos[k]) / span, 0.0, 1.0)
            idx[:, 0], idx[:, 1] = self.line_order[k], self.line_order[k + 1]
            w[:, 0], w[:, 1] = 1 - t, t
            return idx, w
        simplex = self.tri.find_simplex(p)
        inside = simplex >= 0
        if inside.any():
            s = simplex[inside]
            T = self.tri.transform[s]
            b = np.einsum("nij,nj->ni", T[:, :2], p[inside] - T[:, 2])
            bary = np.concatenate([b, 1 - b.sum(1, keepdims=True)], axis=1)
            bary = np.clip(bary, 0.0, None)
            idx[inside] = self.tri.simplices[s]
            w[inside] = bary / bary.sum(1, keepdims=True)
        out = ~inside
        if out.any():
            t, d2 = _segment_closest(p[out], self.hull_a, self.hull_b)
            e = d2.argmin(1)
            te = t[np.arange(len(e)), e]
            idx[out, 0] = self.hull_edges[e, 0]
            idx[out, 1] = self.hull_edges[e, 1]
            w[out, 0] = 1 - te
            w[out, 1] = te
        return idx, w

    def dense(self, view_dirs: np.ndarray) -> np.ndarray:
        """(N, C) dense camera weights (convenience)."""
        idx, w = self.weights(view_dirs)
        out = np.zeros((len(idx), self.n))
        np.add.at(out, (np.arange(len(idx))[:, None].repeat(3, 1), idx), w)
        return out

    def outside(self, view_dirs: np.ndarray) -> np.ndarray:
        """(N,) True where a view lies outside the cameras' hull (the fall-back was used)."""
        p = to_chart(np.asarray(view_dirs, np.float64).reshape(-1, 3))
        if self.tri is None:
            return np.ones(len(p), bool) if self.kind == "line" else np.zeros(len(p), bool)
        return self.tri.find_simplex(p) < 0

    # ------------------------------------------------------------------ Dr.Jit
    def weights_jit(self, view):
        """Dr.Jit version of :meth:`weights` for a Vector3f of view directions (world).

        Returns ([UInt32]*3 camera indices, [Float]*3 weights). The loops over the
        (few) triangles and hull edges are unrolled into the kernel.
        """
        import drjit as dr

        from ..variant import ensure_variant

        mi = ensure_variant()
        Float, UInt32 = mi.Float, mi.UInt32
        d = dr.normalize(view)
        yaw = dr.atan2(d.x, d.z)
        pitch = dr.asin(dr.clip(d.y, -1.0, 1.0))
        n = dr.width(yaw)
        ids = [dr.zeros(UInt32, n) for _ in range(3)]
        w = [dr.full(Float, 1.0, n), dr.zeros(Float, n), dr.zeros(Float, n)]
        if self.kind == "single":
            return ids, w
        if self.kind == "line":
            ax, org = [float(x) for x in self.line_axis], [float(x) for x in self.line_origin]
            s = (yaw - org[0]) * ax[0] + (pitch - org[1]) * ax[1]
            pos = [float(x) for x in self.line_pos]
            k = dr.zeros(UInt32, n)
            for j in range(1, len(pos) - 1):
                k = dr.select(s >= pos[j], UInt32(j), k)
            lo = dr.zeros(Float, n)
            hi = dr.zeros(Float, n)
            a_id = dr.zeros(UInt32, n)
            b_id = dr.zeros(UInt32, n)
            for j in range(len(pos) - 1):
                sel = k == j
                lo = dr.select(sel, pos[j], lo)
                hi = dr.select(sel, pos[j + 1], hi)
                a_id = dr.select(sel, UInt32(int(self.line_order[j])), a_id)
                b_id = dr.select(sel, UInt32(int(self.line_order[j + 1])), b_id)
            t = dr.clip((s - lo) / dr.maximum(hi - lo, Float(1e-30)), 0.0, 1.0)
            return [a_id, b_id, ids[2]], [1 - t, t, w[2]]
        found = dr.zeros(mi.Bool, n)
        for t_i, simplex in enumerate(self.tri.simplices):
            T = [[float(x) for x in row] for row in self.tri.transform[t_i]]
            b0 = T[0][0] * (yaw - T[2][0]) + T[0][1] * (pitch - T[2][1])
            b1 = T[1][0] * (yaw - T[2][0]) + T[1][1] * (pitch - T[2][1])
            b2 = 1 - b0 - b1
            inside = ~found & (b0 >= -1e-7) & (b1 >= -1e-7) & (b2 >= -1e-7)
            bb = [dr.maximum(b0, Float(0)), dr.maximum(b1, Float(0)), dr.maximum(b2, Float(0))]
            tot = bb[0] + bb[1] + bb[2]
            for k in range(3):
                ids[k] = dr.select(inside, UInt32(int(simplex[k])), ids[k])
                w[k] = dr.select(inside, bb[k] / tot, w[k])
            found |= inside
        best = dr.full(Float, dr.inf, n)
        e_a = dr.zeros(UInt32, n)
        e_b = dr.zeros(UInt32, n)
        e_t = dr.zeros(Float, n)
        for (ia, ib), a, b in zip(self.hull_edges, self.hull_a, self.hull_b):
            a, b = [float(x) for x in a], [float(x) for x in b]
            ab = [b[0] - a[0], b[1] - a[1]]
            denom = max(ab[0] * ab[0] + ab[1] * ab[1], 1e-300)
            t = dr.clip(((yaw - a[0]) * ab[0] + (pitch - a[1]) * ab[1]) / denom, 0.0, 1.0)
            qx, qy = a[0] + t * ab[0], a[1] + t * ab[1]
            dist = (yaw - qx) ** 2 + (pitch - qy) ** 2
            closer = dist < best
            best = dr.select(closer, dist, best)
            e_a = dr.select(closer, UInt32(int(ia)), e_a)
            e_b = dr.select(closer, UInt32(int(ib)), e_b)
            e_t = dr.select(closer, t, e_t)
        out = ~found
        ids[0] = dr.select(out, e_a, ids[0])
        ids[1] = dr.select(out, e_b, ids[1])
        ids[2] = dr.select(out, UInt32(0), ids[2])
        w[0] = dr.select(out, 1 - e_t, w[0])
        w[1] = dr.select(out, e_t, w[1])
        w[2] = dr.select(out, 0.0, w[2])
        return ids, w
