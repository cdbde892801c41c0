"""Phong tessellation: a curved surface over a coarse triangle mesh from its vertex normals.

Boubekeur, T. and Alexa, M. (2008), "Phong Tessellation", ACM Transactions on Graphics 27(5)
(SIGGRAPH Asia), 141. A point of a triangle with barycentrics ``b = (b0, b1, b2)`` over vertices
``P_i`` with unit normals ``N_i`` is

    p(b)  = Σ b_i P_i                                  (the flat triangle)
    π_i(p) = p − ((p − P_i) · N_i) N_i                 (p projected onto vertex i's tangent plane)
    p*(b) = (1 − α) p + α Σ b_i π_i(p)                 (shape factor α)

a quadratic patch that interpolates the vertices, meets its neighbours along each edge (an edge's
points depend only on its two vertices), and on a convex stretch bulges out of the chords — which lie
*inside* a smooth subject's skin by the sag ``l² / 8r`` of an edge of length ``l`` on curvature
radius ``r`` (0.36 mm for a 16-mm edge on a 9-cm head: about a third of a 256² pixel on its outline).

:class:`PhongTessellation` splits every triangle ``level`` times along each edge (``level²``
sub-triangles; vertices on an edge are shared by both triangles, so the surface is watertight),
evaluates ``p*`` at the sub-vertices for given vertex positions, and maps a hit on a sub-triangle back
to the coarse triangle and its barycentrics — everything downstream (shading, lit images, fields)
stays on the coarse mesh. ``level = 1`` is the coarse mesh itself. Units: whatever the positions are
in (metres throughout mifacerf).
"""
from __future__ import annotations

import numpy as np

#: the shape factor (0: flat). The paper recommends 3/4 for looks; for a surface, 1/2 is the one that
#: puts an edge's midpoint on the circle through its ends: with ends at half-angle θ on a unit circle,
#: normals radial, the midpoint lands at radius cos θ (1 + α sin² θ) = 1 + (α − 1/2) θ² + O(θ⁴). 3/4
#: overshoots by half the chord's sag (tests/test_phong.py measures both on a sphere).
ALPHA = 0.5


class PhongTessellation:
    """The sub-division of a triangle mesh's ``faces`` (F, 3) over ``n_vertices`` vertices at ``level`` ≥ 1.

    ``only`` (F,) bool, optional: the faces to curve and split (others pass as one sub-face each, flat,
    e.g. the eyes and teeth of a combined scene). ``normals_from`` (F,) bool, optional: the faces whose
    area-weighted normals make the vertex normals (default: ``only``) — a scene that curves part of a
    surface gives those faces the same sub-faces as the whole surface curved, by passing the whole surface
    here. Attributes: ``faces`` (F', 3) the sub-faces over the
    sub-vertices; ``parent`` (F',) each sub-face's coarse face; ``corner_bary`` (F', 3, 3) its corners'
    barycentrics in that face; ``n_sub`` the number of sub-vertices (the coarse vertices come first, in
    their order)."""

    def __init__(self, faces, n_vertices: int, level: int = 3, only=None, alpha: float = ALPHA, normals_from=None):
        F = np.asarray(faces, np.int64).reshape(-1, 3)
        if level < 1 or int(level) != level:
            raise ValueError(f"level must be a whole number >= 1, got {level!r}")
        if F.size and (F.min() < 0 or F.max() >= n_vertices):
            raise ValueError(f"faces index vertices out of range (n_vertices = {n_vertices})")
        self.level, self.alpha, self.n_vertices = int(level), float(alpha), int(n_vertices)
        self.coarse = F
        curve = np.ones(len(F), bool) if only is None else np.asarray(only, bool)
        if curve.shape != (len(F),):
            raise ValueError(f"only has shape {curve.shape}; expected ({len(F)},)")
        self.curved = curve
        normals_from = curve if normals_from is None else np.asarray(normals_from, bool)
        if normals_from.shape != (len(F),):
            raise ValueError(f"normals_from has shape {normals_from.shape}; expected ({len(F)},)")
        self.normals_from = normals_from
        n = self.level
        # the sub-vertices of one triangle on the (n+1)-point lattice: (i, j) with i + j <= n, weights
        # b = ((n - i - j), i, j) / n over its corners (0, 1, 2)
        lattice = [(i, j) for j in range(n + 1) for i in range(n + 1 - j)]
        where = {ij: k for k, ij in enumerate(lattice)}
        tri_local = []
        for j in range(n):
            for i in range(n - j):
                tri_local.append((where[i, j], where[i + 1, j], where[i, j + 1]))
                if i + j < n - 1:
                    tri_local.append((where[i + 1, j], where[i + 1, j + 1], where[i, j + 1]))
        tri_local = np.asarray(tri_local, np.int64)
        lat = np.asarray(lattice, np.float64)
        lat_bary = np.stack([n - lat[:, 0] - lat[:, 1], lat[:, 0], lat[:, 1]], 1) / n

        # one id per sub-vertex: a coarse vertex; a point inside an (unordered) edge; a point inside a face
        ids = {}
        src_face, src_bary = [], []            # how each sub-vertex is evaluated (a face and barycentrics)
        for v in range(n_vertices):
            ids[("v", v)] = v
        src_face = [-1] * n_vertices
        src_bary = [None] * n_vertices
        sub_faces, parent, corner_bary = [], [], []
        for f, (a, b, c) in enumerate(F):
            corners = (a, b, c)
            if not curve[f]:
                sub_faces.append((a, b, c))
                parent.append(f)
                corner_bary.append(np.eye(3))
                continue
            local_ids = np.empty(len(lattice), np.int64)
            for k, (i, j) in enumerate(lattice):
                w = lat_bary[k]
                nz = np.flatnonzero(w > 0)
                if len(nz) == 1:
                    key = ("v", corners[nz[0]])
                elif len(nz) == 2:
                    u, v = corners[nz[0]], corners[nz[1]]
                    # the point's position along the edge from its lower-numbered vertex: a lattice step count
                    t = int(round(n * (w[nz[1]] if u < v else w[nz[0]])))
                    key = ("e", min(u, v), max(u, v), t)
                else:
                    key = ("f", f, k)
                if key not in ids:
                    ids[key] = len(src_face)
                    src_face.append(f)
                    src_bary.append(w)
                local_ids[k] = ids[key]
            for t in tri_local:
                sub_faces.append(tuple(local_ids[t]))
                parent.append(f)
                corner_bary.append(lat_bary[t])
        self.faces = np.asarray(sub_faces, np.int64).reshape(-1, 3)
        self.parent = np.asarray(parent, np.int64)
        self.corner_bary = np.asarray(corner_bary, np.float64).reshape(-1, 3, 3)
        self.n_sub = len(src_face)
        extra = np.arange(n_vertices, self.n_sub)
        self._extra_face = np.asarray(src_face, np.int64)[extra]
        self._extra_bary = np.asarray([src_bary[k] for k in extra], np.float64).reshape(-1, 3)

    def positions(self, V, N=None) -> np.ndarray:
        """The sub-vertices (n_sub, 3) on the Phong surface of vertex positions ``V`` (n_vertices, 3) with unit
        normals ``N`` (default: the area-weighted vertex normals of the faces ``normals_from``, the curved ones
        unless told). A vertex with a zero
        normal (in no curved face) contributes its flat point."""
        V = np.asarray(V, np.float64)
        if V.shape != (self.n_vertices, 3):
            raise ValueError(f"expected ({self.n_vertices}, 3) vertex positions, got {V.shape}")
        if N is None:
            from .visibility import vertex_normals

            N = vertex_normals(V, self.coarse[self.normals_from])
        N = np.asarray(N, np.float64)
        out = np.empty((self.n_sub, 3))
        out[:self.n_vertices] = V
        if len(self._extra_face):
            corners = self.coarse[self._extra_face]                    # (E, 3)
            P, Nc, b = V[corners], N[corners], self._extra_bary        # (E, 3, 3), (E, 3, 3), (E, 3)
            p = np.einsum("ek,ekd->ed", b, P)
            proj = p[:, None, :] - np.einsum("ekd,ekd->ek", p[:, None, :] - P, Nc)[..., None] * Nc
            q = np.einsum("ek,ekd->ed", b, proj)
            out[self.n_vertices:] = (1.0 - self.alpha) * p + self.alpha * q
        return out

    def to_coarse(self, tri, bary) -> tuple[np.ndarray, np.ndarray]:
        """Hits on sub-faces → (coarse faces (N,), barycentrics in them (N, 3)). ``tri`` (N,) sub-face ids
        (−1: no hit, kept −1 with zero barycentrics), ``bary`` (N, 3)."""
        tri = np.asarray(tri, np.int64)
        bary = np.asarray(bary, np.float64)
        ok = tri >= 0
        out_tri = np.full(len(tri), -1, np.int64)
        out_bary = np.zeros((len(tri), 3))
        out_tri[ok] = self.parent[tri[ok]]
        out_bary[ok] = np.einsum("nk,nkd->nd", bary[ok], self.corner_bary[tri[ok]])
        return out_tri, out_bary

    def device_map(self, mi) -> tuple:
        """``parent`` (UInt32) and ``corner_bary`` (Float, 9 per sub-face) as device arrays, for
        :func:`to_coarse_device`."""
        from ..jitarrays import to_jit

        return (to_jit(mi.UInt32, self.parent.astype(np.uint32)),
                to_jit(mi.Float, self.corner_bary.reshape(-1).astype(np.float32)))


def to_coarse_device(mi, maps, sub, b, active=True):
    """:meth:`PhongTessellation.to_coarse` on the device, inside a ray cast's kernel: sub-face hits ``sub``
    (UInt32) with barycentrics ``b`` [3 Float] → (coarse faces (UInt32), their barycentrics [3 Float]), the
    latter Σ_k b_k × sub-face corner k's; ``maps`` from :meth:`PhongTessellation.device_map`."""
    import drjit as dr

    parent, corners = maps
    tri = dr.gather(mi.UInt32, parent, sub, active)
    return tri, [sum(b[k] * dr.gather(mi.Float, corners, sub * 9 + 3 * k + j, active) for k in range(3))
                 for j in range(3)]


def check_curved(curved) -> int:
    """``curved`` (a Phong level: splits per edge, 1 the flat triangles) as an int; ``ValueError`` naming it
    unless it is a whole number >= 1 (a bool is refused)."""
    if isinstance(curved, bool) or not isinstance(curved, (int, float, np.integer, np.floating)) \
            or int(curved) != curved or curved < 1:
        raise ValueError(f"curved must be a whole number >= 1 (1: flat triangles), got {curved!r}")
    return int(curved)


def surface_entry(curved: int = 1) -> dict:
    """The ``surface`` entry of registration.json and model.json: the surface a registration fitted the
    outlines against and renders trace (``{"method": "phong" / "flat", "curved": level}``)."""
    curved = check_curved(curved)
    return {"method": "phong" if curved > 1 else "flat", "curved": curved}


__all__ = ["ALPHA", "PhongTessellation", "check_curved", "surface_entry", "to_coarse_device"]
