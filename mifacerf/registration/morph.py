"""3-D morphs that carry points from one expression to another (paper §4.1, §3).

:class:`CoarseMorph` — the paper's initial estimate: "a 3D morph of p's position in R ...
computed using the positions of corresponding triangles of the coarse mesh in R and N,
analogous to the 2D morph presented in [BN92]" (Beier & Neely 1992, field morphing).
In 2-D each line pair gives a point coordinates (u along the line, v perpendicular, in
absolute units) and the morphed point is the weighted mean of each pair's answer.
In 3-D each coarse triangle ``(a, b, c)`` plays the line's role: a point ``p`` gets
coordinates ``p = a + u (b - a) + v (c - a) + h n`` (``n`` the unit normal; ``h`` in
metres, as BN92 keeps the perpendicular distance absolute); in the other expression
``p' = a' + u (b' - a') + v (c' - a') + h n'``. Weights, BN92's form with the triangle's
size ``sqrt(area)`` for the line length: ``w = (size^P / (A + dist))^B`` with ``dist``
the distance from ``p`` to the triangle. Properties (tested): every rigid motion and
every translation is reproduced exactly; a planar coarse mesh under any affine map of
its plane carries points of that plane exactly.

The moving-least-squares affine deformation that places the template's extra vertices
(nostrils, lips, eyelids, ears) relative to the registered fiducials is on the ground floor,
:func:`mifacerf.geometry.schaefer2006.mls_affine` (Schaefer et al. 2006).

:func:`deformation_distances` / :func:`choose_references` — the paper's "distance-weighted
version of the deformation metric described in Section 5": per coarse point, the
difference between two expressions' coarse neighbourhoods after each is rigidly aligned
(Horn 1987) onto the neutral's; per dense point, those differences weighted by distance.
"""
from __future__ import annotations

import numpy as np

from ..geometry.horn1987 import horn


# --------------------------------------------------------------------------------- geometry helpers
def triangle_frames(V: np.ndarray, F: np.ndarray):
    """Per triangle: origin (F, 3), basis (F, 3, 3) columns ``(b-a, c-a, n)``, area (F,)."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    e1, e2 = b - a, c - a
    n = np.cross(e1, e2)
    area2 = np.linalg.norm(n, axis=1)
    n = n / np.maximum(area2, 1e-300)[:, None]
    return a, np.stack([e1, e2, n], axis=-1), 0.5 * area2


def point_triangle_distance(P: np.ndarray, A: np.ndarray, B: np.ndarray, C: np.ndarray) -> np.ndarray:
    """Distances (M, F) from points P (M, 3) to triangles (A, B, C) (each (F, 3)). Ericson's regions."""
    P = P[:, None, :]
    ab, ac, ap = B - A, C - A, P - A
    d1, d2 = np.einsum("fk,mfk->mf", ab, ap), np.einsum("fk,mfk->mf", ac, ap)
    bp = P - B
    d3, d4 = np.einsum("fk,mfk->mf", ab, bp), np.einsum("fk,mfk->mf", ac, bp)
    cp = P - C
    d5, d6 = np.einsum("fk,mfk->mf", ab, cp), np.einsum("fk,mfk->mf", ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    denom = va + vb + vc
    with np.errstate(divide="ignore", invalid="ignore"):
        v = vb / denom
        w = vc / denom
    Q = A + v[..., None] * ab + w[..., None] * ac  # interior
    # vertex and edge regions
    conds = []
    with np.errstate(divide="ignore", invalid="ignore"):
        conds.append(((d1 <= 0) & (d2 <= 0), np.broadcast_to(A, Q.shape)))
        conds.append(((d3 >= 0) & (d4 <= d3), np.broadcast_to(B, Q.shape)))
        conds.append(((d6 >= 0) & (d5 <= d6), np.broadcast_to(C, Q.shape)))
        t = d1 / (d1 - d3)
        conds.append(((vc <= 0) & (d1 >= 0) & (d3 <= 0), A + t[..., None] * ab))
        t = d2 / (d2 - d6)
        conds.append(((vb <= 0) & (d2 >= 0) & (d6 <= 0), A + t[..., None] * ac))
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        conds.append(((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), B + t[..., None] * (C - B)))
    done = np.zeros(Q.shape[:2], bool)
    out = Q.copy()
    for cond, q in conds:
        m = cond & ~done
        out[m] = q[m]
        done |= m
    return np.linalg.norm(P - out, axis=-1)


# --------------------------------------------------------------------------------- the coarse morph
class CoarseMorph:
    """Beier–Neely-style 3-D morph defined by corresponding coarse triangles.

    ``src`` (K, 3), ``dst`` (K, 3) coarse points in the two expressions; ``triangles`` (F, 3)
    (triangles with a NaN corner in either expression are ignored). ``a`` (metres), ``b``,
    ``p``: BN92's constants (``a`` the smoothness scale, ``b`` how fast weight falls off with
    distance, ``p`` the influence of size).
    """

    def __init__(self, src, dst, triangles, a: float = 0.004, b: float = 2.0, p: float = 0.5):
        self.src = np.asarray(src, np.float64)
        self.dst = np.asarray(dst, np.float64)
        F = np.asarray(triangles, np.int64).reshape(-1, 3)
        good = np.isfinite(self.src[F]).all((1, 2)) & np.isfinite(self.dst[F]).all((1, 2))
        self.triangles = F[good]
        if len(self.triangles) == 0:
            raise ValueError("the coarse mesh has no usable triangle (too many coarse points missing)")
        self.o_s, self.B_s, area_s = triangle_frames(self.src, self.triangles)
        self.o_d, self.B_d, _ = triangle_frames(self.dst, self.triangles)
        ok = area_s > 1e-12
        self.triangles, self.o_s, self.B_s, self.o_d, self.B_d = (x[ok] for x in (
            self.triangles, self.o_s, self.B_s, self.o_d, self.B_d))
        self.size = np.sqrt(area_s[ok])
        self.Binv_s = np.linalg.inv(self.B_s)
        self.a, self.b, self.p = a, b, p

    def weights(self, points: np.ndarray) -> np.ndarray:
        """(M, F) normalised BN92 weights of every triangle for every point (source positions)."""
        T = self.triangles
        d = point_triangle_distance(points, self.src[T[:, 0]], self.src[T[:, 1]], self.src[T[:, 2]])
        w = (self.size[None] ** self.p / (self.a + d)) ** self.b
        return w / w.sum(1, keepdims=True)

    def __call__(self, points, chunk: int = 4096) -> np.ndarray:
        """Morph points (M, 3) from the source expression to the destination."""
        P = np.asarray(points, np.float64).reshape(-1, 3)
        out = np.empty_like(P)
        for s in range(0, len(P), chunk):
            Q = P[s:s + chunk]
            coords = np.einsum("fij,mfj->mfi", self.Binv_s, Q[:, None, :] - self.o_s[None])  # (M, F, 3)
            pred = self.o_d[None] + np.einsum("fij,mfj->mfi", self.B_d, coords)
            w = self.weights(Q)
            out[s:s + chunk] = np.einsum("mf,mfi->mi", w, pred)
        return out


# --------------------------------------------------------------------------------- reference choice
def coarse_neighbourhoods(n_points: int, triangles) -> list[np.ndarray]:
    """Each coarse point with its neighbours in the coarse mesh (sorted index arrays)."""
    nb = [set([i]) for i in range(n_points)]
    for t in np.asarray(triangles, np.int64).reshape(-1, 3):
        for i in t:
            nb[i].update(int(j) for j in t)
    return [np.array(sorted(s)) for s in nb]


def deformation_distances(neutral, A, B, nbhds) -> np.ndarray:
    """(K,) per coarse point: RMS difference of its neighbourhood in ``A`` and ``B`` (each (K, 3)),
    both rigidly aligned onto ``neutral`` first (the §5 local deformation). NaN where unknown."""
    out = np.full(len(nbhds), np.nan)
    for j, ids in enumerate(nbhds):
        m = np.isfinite(A[ids]).all(1) & np.isfinite(B[ids]).all(1) & np.isfinite(neutral[ids]).all(1)
        ids = ids[m]
        if len(ids) < 3 or not m[list(nbhds[j]).index(j)]:
            continue
        Ra, ta = horn(A[ids], neutral[ids])
        Rb, tb = horn(B[ids], neutral[ids])
        da = A[ids] @ Ra.T + ta
        db = B[ids] @ Rb.T + tb
        out[j] = np.sqrt(np.mean(np.sum((da - db) ** 2, axis=1)))
    return out


def choose_references(points_neutral, coarse_neutral, distances: np.ndarray, sigma: float = 0.02) -> np.ndarray:
    """Per point the index of the most similar reference expression.

    ``points_neutral`` (M, 3) the points' positions in the neutral; ``coarse_neutral`` (K, 3);
    ``distances`` (n_ref, K) deformation distances of each reference to the new expression
    (NaN = unknown). Weights ``exp(-d² / 2σ²)`` with ``d`` the neutral distance to each coarse
    point (a floor keeps far points using their nearest coarse points).
    """
    P = np.asarray(points_neutral, np.float64)
    Cn = np.asarray(coarse_neutral, np.float64)
    D = np.asarray(distances, np.float64)
    d2 = ((P[:, None] - Cn[None]) ** 2).sum(-1)                 # (M, K)
    d2 = d2 - np.nanmin(d2, axis=1, keepdims=True)              # relative: nearest gets weight 1
    w = np.exp(-d2 / (2 * sigma ** 2))
    w = np.where(np.isfinite(Cn).all(1)[None], w, 0.0)
    known = np.isfinite(D)
    Dz = np.where(known, D, 0.0)
    num = np.einsum("mk,rk->rm", w, Dz)
    den = np.einsum("mk,rk->rm", w, known.astype(float))
    score = np.where(den > 1e-12, num / np.maximum(den, 1e-300), np.inf)
    return np.argmin(score, axis=0)
