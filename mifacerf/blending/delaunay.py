"""m-dimensional triangulation of projected source deformations, barycentrics, out-of-hull rule (paper §5).

:func:`triangulate` turns the ``n`` source coordinates of one vertex (``m <= 3``)
into a :class:`LocalTriangulation`.  Everything downstream (the Dr.Jit evaluator,
the NumPy reference) reads these arrays only.

Robustness rules (each one documented here and tested):

1. **Duplicates.**  Points closer than ``dup_tol`` (in the coordinates' units,
   i.e. relative to the PCA scale) are merged.  The representative of a cluster
   is the ``preferred`` id (the neutral) when it is in the cluster, otherwise the
   smallest id.  A duplicated source used as a target gets its weight on the
   representative (whose local deformation is the same to within ``dup_tol``).
2. **m = 0** (a single distinct point): one 0-simplex; every target gets weight 1
   on its representative.
3. **m = 1**: the sorted distinct coordinates; the intervals between neighbours
   are the simplices.
4. **m = 2, 3**: ``scipy.spatial.Delaunay`` (qhull, default options) first.  The
   result is accepted only if every point is a vertex, every simplex is
   non-degenerate (Hadamard ratio ``|det A| / Π|a_j| >= flat_tol``) and the
   simplices' volumes add up to the convex hull's.  Otherwise (cospherical
   lattices make qhull's ``Qt`` emit flat simplices; precision errors raise
   ``QhullError``) a **regular triangulation** is built from the lower convex hull
   of the points lifted to ``|p - c|² + ε_i`` with tiny deterministic ``ε_i``,
   which breaks cospherical ties without moving any point; then qhull's joggle
   (``QJ``) is tried.  If no attempt passes the checks the dimension is
   **degraded** to ``m - 1`` (the leading ``m - 1`` PCA coordinates) and the
   procedure repeats; ``m = 1`` always succeeds.  ``LocalTriangulation.method``
   records what was used.
4b. **Slivers.**  Near-coplanar points on the hull make qhull emit boundary
   simplices of almost zero volume (Hadamard ratios of 1e-13 occur on smooth
   data).  Their barycentric coordinates are hypersensitive (a weight can swing
   from 0 to 1 over a nanometre of deformation) and meaningless in float32.
   Boundary simplices with ratio below ``SLIVER_TOL`` are therefore marked as
   **ghosts** (repeatedly, as marking exposes others), unless that would leave a
   point in ghosts only.  Ghosts stay in the triangulation, which therefore
   stays convex and walkable, but a target that lands in a ghost counts as
   *outside*: it gets the weights of the nearest point on the boundary of the
   non-ghost simplices (``facets``).  The difference from the ghost's own
   barycentrics is bounded by the ghost's thickness.
5. **Outside the hull**: a target is moved to the nearest point of the convex
   hull (unique, so continuous in the target) and weighted by that point's
   barycentric coordinates in its hull facet.  Inside, the weights are the
   barycentric coordinates in the containing simplex, which are continuous
   across simplices; hence the weights are continuous everywhere, non-negative
   and sum to 1.  Barycentrics within ``-inside_tol`` of zero count as inside
   and are clamped to zero and renormalised.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import ConvexHull, Delaunay, QhullError

from ..geometry.ericson2004 import region_barycentrics

__all__ = [
    "LocalTriangulation",
    "triangulate",
    "merge_duplicates",
    "simplex_transforms",
    "barycentric_bruteforce",
    "nearest_on_hull",
    "weights_numpy",
]

#: Hadamard-ratio threshold under which a simplex counts as flat (the triangulation is rejected)
FLAT_TOL = 1e-12
#: boundary simplices flatter than this become ghosts (see rule 4b)
SLIVER_TOL = 1e-3
#: relative tolerance on "simplex volumes add up to the hull's"
VOLUME_RTOL = 1e-8
#: default duplicate-merging distance (units of the PCA scale)
DUP_TOL = 1e-7
#: relative size of the lifting perturbation of the regular-triangulation fallback
LIFT_EPS = 1e-9


@dataclass
class LocalTriangulation:
    """Triangulation of one vertex's projected sources.

    Attributes
    ----------
    m : int                         dimension (0..3)
    points : ``(p, m)`` float64      distinct source coordinates
    point_ids : ``(p,)`` int64        id (source index) of each point
    merged : ``(n,)`` int64           for each input point, the index of its representative in ``points``
    simplices : ``(S, m+1)`` int64    point indices (``S = 1``, ``[[0]]`` for ``m = 0``)
    transform : ``(S, m+1, m)``       scipy convention: ``b[:m] = T (x - r)``, ``b[m] = 1 - Σ b[:m]`` with
                                      ``T = transform[s, :m]``, ``r = transform[s, m]``
    neighbors : ``(S, m+1)`` int64    simplex across the facet opposite vertex ``j`` (-1: hull boundary)
    ghost : ``(S,)`` bool             boundary slivers (rule 4b): a target inside one counts as outside
    facets : ``(H, m)`` int64         boundary facets of the non-ghost simplices; empty for ``m = 0``
    start : int                     simplex where walks start (contains the points' centroid)
    method : str                    "point", "intervals", "delaunay", "regular", "joggle" (+ " (degraded from m=k)")
    """

    m: int
    points: np.ndarray
    point_ids: np.ndarray
    merged: np.ndarray
    simplices: np.ndarray
    transform: np.ndarray
    neighbors: np.ndarray
    ghost: np.ndarray
    facets: np.ndarray
    start: int
    method: str
    #: the scipy ``Delaunay`` whose simplices these are, when qhull's Delaunay was used (not saved; the
    #: reference evaluator calls its ``find_simplex``)
    qhull: object = field(default=None, repr=False, compare=False)

    @property
    def n_simplices(self) -> int:
        return int(self.simplices.shape[0])


# --------------------------------------------------------------------------------------------- helpers
def merge_duplicates(coords, ids, preferred=None, tol: float = DUP_TOL):
    """Merge points closer than ``tol``.

    Returns ``(points (p, m), point_ids (p,), merged (n,))``; see rule 1 of the module docstring.
    """
    X = np.asarray(coords, dtype=np.float64)
    ids = np.asarray(ids, dtype=np.int64)
    n = X.shape[0]
    order = sorted(range(n), key=lambda i: (ids[i] != preferred, ids[i]))
    merged = np.full(n, -1, dtype=np.int64)
    reps = []
    for i in order:
        if merged[i] >= 0:
            continue
        d = np.sqrt(np.sum((X - X[i]) ** 2, axis=1)) if X.shape[1] else np.zeros(n)
        take = (merged < 0) & (d <= tol)
        merged[take] = len(reps)
        reps.append(i)
    reps = np.array(reps, dtype=np.int64)
    return X[reps].copy(), ids[reps].copy(), merged


def simplex_transforms(points, simplices):
    """scipy-convention barycentric transforms ``(S, m+1, m)`` and Hadamard ratios ``(S,)``.

    Flat simplices (ratio below :data:`FLAT_TOL`) get a zero ``T`` (never NaN).
    """
    P = np.asarray(points, dtype=np.float64)
    S = np.asarray(simplices)
    m = P.shape[1]
    r = P[S[:, m]]                                              # (S, m)
    A = np.transpose(P[S[:, :m]] - r[:, None, :], (0, 2, 1))    # columns v_j - v_m
    if m == 0:
        return np.zeros((S.shape[0], 1, 0)), np.ones(S.shape[0])
    det = np.linalg.det(A)
    colnorm = np.prod(np.linalg.norm(A, axis=1), axis=1)
    ratio = np.abs(det) / np.where(colnorm > 0, colnorm, 1.0)
    ratio = np.where(colnorm > 0, ratio, 0.0)
    good = ratio >= FLAT_TOL
    T = np.zeros_like(A)
    if np.any(good):
        T[good] = np.linalg.inv(A[good])
    return np.concatenate([T, r[:, None, :]], axis=1), ratio


def _boundary_facets(simplices, neighbors, ghost):
    """Facets of non-ghost simplices whose other side is the outside or a ghost: ``(H, m)``."""
    across_ghost = np.where(neighbors >= 0, ghost[np.maximum(neighbors, 0)], True)
    s, j = np.nonzero(~ghost[:, None] & across_ghost)
    m1 = simplices.shape[1]
    keep = np.ones((s.size, m1), dtype=bool)
    keep[np.arange(s.size), j] = False
    return simplices[s][keep].reshape(s.size, m1 - 1)


def _hull_volume(points):
    return float(ConvexHull(points).volume)


def _valid(points, simplices, neighbors, ghost) -> bool:
    """Every point in a non-ghost simplex, no flat simplex, symmetric neighbours, volumes fill the hull."""
    p, m = points.shape
    if simplices.size == 0 or np.unique(simplices[~ghost]).size != p:
        return False
    T, ratio = simplex_transforms(points, simplices)
    if np.any(ratio < FLAT_TOL) or not np.all(np.isfinite(T)):
        return False
    A = points[simplices[:, :m]] - points[simplices[:, m:]]
    vol = np.abs(np.linalg.det(A)).sum() / np.prod(np.arange(1, m + 1))
    try:
        hv = _hull_volume(points)
    except QhullError:
        return False
    if not abs(vol - hv) <= VOLUME_RTOL * max(hv, 1e-300):
        return False
    S = simplices.shape[0]
    nb = neighbors
    if np.any(nb >= S):
        return False
    for j in range(m + 1):
        ok = nb[:, j] < 0
        back = nb[np.maximum(nb[:, j], 0)]
        ok |= np.any(back == np.arange(S)[:, None], axis=1)
        if not np.all(ok):
            return False
    return True


def mark_slivers(points, simplices, neighbors, tol: float = SLIVER_TOL) -> np.ndarray:
    """Ghost mask ``(S,)`` of boundary slivers (rule 4b): Hadamard ratio < ``tol``, peeled from the outside in."""
    S, N = simplices, neighbors
    _, ratio = simplex_transforms(points, S)
    ghost = np.zeros(S.shape[0], dtype=bool)
    uses = np.bincount(S.ravel(), minlength=points.shape[0])
    changed = True
    while changed:
        changed = False
        exposed = np.any(np.where(N >= 0, ghost[np.maximum(N, 0)], True), axis=1)
        cand = np.nonzero(~ghost & (ratio < tol) & exposed)[0]
        for s in cand[np.argsort(ratio[cand])]:
            if np.any(uses[S[s]] <= 1):
                continue
            ghost[s] = True
            uses[S[s]] -= 1
            changed = True
    return ghost


def _try_delaunay(points, options):
    try:
        tri = Delaunay(points, qhull_options=options)
    except (QhullError, ValueError, IndexError):
        return None
    S = tri.simplices.astype(np.int64)
    N = tri.neighbors.astype(np.int64)
    if S.size and S.max() >= len(points):   # on (nearly) flat input qhull can keep its point at infinity (Qz)
        return None
    ghost = mark_slivers(points, S, N)
    if not _valid(points, S, N, ghost):
        return None
    return S, N, ghost, tri


def _try_regular(points):
    p, m = points.shape
    c = points.mean(axis=0)
    lift = np.sum((points - c) ** 2, axis=1)
    span = max(float(lift.max()), 1e-300)
    # deterministic pseudo-random perturbations in [0, 1) (a structured sequence such as i·φ mod 1 is
    # nearly affine in a lattice's coordinates and would not break its cospherical ties)
    eps = LIFT_EPS * span * np.random.default_rng(20040601).random(p)
    try:
        hull = ConvexHull(np.c_[points, lift + eps], qhull_options="Qbb Qc Qt")
    except (QhullError, ValueError):
        return None
    lower = hull.equations[:, m] < -1e-12
    if not np.any(lower):
        return None
    new_id = np.full(lower.size, -1, dtype=np.int64)
    new_id[lower] = np.arange(int(lower.sum()))
    S = hull.simplices[lower].astype(np.int64)
    N = hull.neighbors[lower].astype(np.int64)
    N = np.where(N >= 0, new_id[np.maximum(N, 0)], -1)
    ghost = mark_slivers(points, S, N)
    if not _valid(points, S, N, ghost):
        return None
    return S, N, ghost, None


def _locate_start(points, simplices, transform, ghost):
    c = points.mean(axis=0)
    b = _bary(transform, np.broadcast_to(c, (simplices.shape[0], points.shape[1])))
    score = np.where(ghost, -np.inf, b.min(axis=1))
    return int(np.argmax(score))


def _bary(transform, x):
    """Barycentrics ``(..., m+1)`` of points ``x`` ``(..., m)`` in simplices with ``transform`` ``(..., m+1, m)``."""
    m = x.shape[-1]
    c = np.einsum("...ij,...j->...i", transform[..., :m, :], x - transform[..., m, :])
    return np.concatenate([c, 1.0 - c.sum(axis=-1, keepdims=True)], axis=-1)


# --------------------------------------------------------------------------------------------- main
def triangulate(coords, ids=None, preferred=None, dup_tol: float = DUP_TOL) -> LocalTriangulation:
    """Triangulate ``n`` points in ``m <= 3`` dimensions (rules in the module docstring).

    Parameters
    ----------
    coords : array_like, shape ``(n, m)``
        Projected source deformations (PCA coordinates, units of the PCA scale).
    ids : array_like of int, shape ``(n,)``, optional
        Source ids of the points (default ``0..n-1``).
    preferred : int, optional
        Id that represents its duplicate cluster (the neutral).
    dup_tol : float
        Duplicate-merging distance.

    Returns
    -------
    LocalTriangulation, possibly of lower dimension than ``coords`` (see ``.m`` and ``.method``).
    """
    X = np.asarray(coords, dtype=np.float64)
    if X.ndim != 2 or X.shape[1] > 3 or X.shape[0] == 0:
        raise ValueError(f"coords must have shape (n >= 1, m <= 3); got {X.shape}")
    if not np.all(np.isfinite(X)):
        raise ValueError(f"coords {X.shape} contain non-finite values")
    n, m0 = X.shape
    ids = np.arange(n, dtype=np.int64) if ids is None else np.asarray(ids, dtype=np.int64)
    if ids.shape != (n,):
        raise ValueError(f"ids must have shape ({n},); got {ids.shape}")
    m = m0
    degraded = ""
    while True:
        pts, pids, merged = merge_duplicates(X[:, :m], ids, preferred, dup_tol)
        p = pts.shape[0]
        if p <= m:                       # not enough distinct points for an m-simplex
            if m != min(p - 1, m):
                degraded = degraded or f" (degraded from m={m0})"
            m = p - 1
            continue
        if m == 0:
            return LocalTriangulation(
                m=0, points=pts[:, :0], point_ids=pids, merged=merged,
                simplices=np.zeros((1, 1), dtype=np.int64), transform=np.zeros((1, 1, 0)),
                neighbors=np.full((1, 1), -1, dtype=np.int64), ghost=np.zeros(1, dtype=bool),
                facets=np.zeros((0, 0), dtype=np.int64),
                start=0, method="point" + degraded)
        if m == 1:
            order = np.argsort(pts[:, 0], kind="stable")
            S = np.stack([order[:-1], order[1:]], axis=1).astype(np.int64)
            k = S.shape[0]
            N = np.full((k, 2), -1, dtype=np.int64)
            N[:-1, 0] = np.arange(1, k)       # opposite the left end: the next interval
            N[1:, 1] = np.arange(0, k - 1)    # opposite the right end: the previous one
            T, _ = simplex_transforms(pts, S)
            return LocalTriangulation(
                m=1, points=pts, point_ids=pids, merged=merged, simplices=S, transform=T, neighbors=N,
                ghost=np.zeros(k, dtype=bool), facets=np.array([[order[0]], [order[-1]]], dtype=np.int64),
                start=(k - 1) // 2,
                method="intervals" + degraded)
        attempts = (("delaunay", lambda: _try_delaunay(pts, None)),
                    ("regular", lambda: _try_regular(pts)),
                    ("joggle", lambda: _try_delaunay(pts, "QJ")))
        for name, attempt in attempts:
            res = attempt()
            if res is not None:
                S, N, ghost, qh = res
                T, _ = simplex_transforms(pts, S)
                return LocalTriangulation(
                    m=m, points=pts, point_ids=pids, merged=merged, simplices=S, transform=T, neighbors=N,
                    ghost=ghost, facets=_boundary_facets(S, N, ghost), start=_locate_start(pts, S, T, ghost),
                    method=name + degraded, qhull=qh)
        degraded = f" (degraded from m={m0})"
        m -= 1


# ------------------------------------------------------------------------------------- evaluation (NumPy)
def barycentric_bruteforce(tri: LocalTriangulation, x):
    """Containing simplex by brute force: ``(simplex (q,), bary (q, m+1), min_bary (q,))`` for ``x`` ``(q, m)``.

    The non-ghost simplex maximising the smallest barycentric coordinate (> -tol means inside).
    """
    x = np.asarray(x, dtype=np.float64)
    b = _bary(tri.transform[None], x[:, None, :])               # (q, S, m+1)
    mins = np.where(tri.ghost[None, :], -np.inf, b.min(axis=2))
    s = np.argmax(mins, axis=1)
    return s, b[np.arange(x.shape[0]), s], mins[np.arange(x.shape[0]), s]


def closest_on_simplex_facet(x, V):
    """Closest point of each facet to each query: barycentrics and squared distances.

    ``x`` ``(..., m)``, ``V`` ``(..., m, m)`` (``m`` facet vertices of dimension ``m``; broadcast).
    Returns ``(bary (..., m), d2 (...))``.  Facets are points (m=1), segments (m=2) or triangles (m=3).
    """
    m = x.shape[-1]
    if m == 1:
        b = np.ones(np.broadcast_shapes(x.shape[:-1], V.shape[:-2]) + (1,))
        d2 = np.sum((x - V[..., 0, :]) ** 2, axis=-1)
        return b, d2
    if m == 2:
        a, c = V[..., 0, :], V[..., 1, :]
        ab = c - a
        den = np.sum(ab * ab, axis=-1)
        t = np.clip(np.sum((x - a) * ab, axis=-1) / np.where(den > 0, den, 1.0), 0.0, 1.0)
        b = np.stack([1 - t, t], axis=-1)
        d2 = np.sum((x - (a + t[..., None] * ab)) ** 2, axis=-1)
        return b, d2
    a, bb, c = V[..., 0, :], V[..., 1, :], V[..., 2, :]
    u, v, w = _closest_triangle_np(x, a, bb, c)
    p = u[..., None] * a + v[..., None] * bb + w[..., None] * c
    return np.stack([u, v, w], axis=-1), np.sum((x - p) ** 2, axis=-1)


def _closest_triangle_np(p, a, b, c):
    """Ericson's closest point on triangle (Real-Time Collision Detection §5.1.5), as barycentrics."""
    dot = lambda x, y: np.sum(x * y, axis=-1)
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    return region_barycentrics(d1, d2, d3, d4, d5, d6, np.where)


def nearest_on_hull(tri: LocalTriangulation, x):
    """Nearest hull facet and its barycentrics for queries ``x`` ``(q, m)``: ``(facet (q,), bary (q, m), d2 (q,))``."""
    x = np.asarray(x, dtype=np.float64)
    V = tri.points[tri.facets]                                   # (H, m, m)
    b, d2 = closest_on_simplex_facet(x[:, None, :], V[None])     # (q, H, m), (q, H)
    f = np.argmin(d2, axis=1)
    r = np.arange(x.shape[0])
    return f, b[r, f], d2[r, f]


def weights_numpy(tri: LocalTriangulation, x, inside_tol: float = 1e-9):
    """Blend weights of queries ``x`` ``(q, m)`` by brute force: ``(ids (q, m+1), w (q, m+1))``.

    ``ids`` are ``tri.point_ids``; unused slots (outside: the facet has ``m`` vertices) hold weight 0
    and repeat the first id.  This is the slow, obviously-correct definition the vectorised paths are
    tested against.
    """
    x = np.asarray(x, dtype=np.float64)
    q, m = x.shape[0], tri.m
    if m == 0:
        return np.repeat(tri.point_ids[:1][None], q, axis=0), np.ones((q, 1))
    s, b, bmin = barycentric_bruteforce(tri, x)
    ids = tri.point_ids[tri.simplices[s]]
    w = np.clip(b, 0.0, None)
    inside = bmin >= -inside_tol
    out = ~inside
    if np.any(out):
        f, fb, _ = nearest_on_hull(tri, x[out])
        fid = tri.point_ids[tri.facets[f]]
        ids[out] = np.concatenate([fid, fid[:, :1]], axis=1)
        w[out] = np.concatenate([fb, np.zeros((fb.shape[0], 1))], axis=1)
        w[out] = np.clip(w[out], 0.0, None)
    w /= w.sum(axis=1, keepdims=True)
    return ids, w
