"""The 3-D snap-to and the progressive snap-to algorithm (paper §4.1).

**Dot strength** of a 3-D point: project it into every view where it is visible and sum
the dot-strength maps (:mod:`.dots`) there, bilinearly sampled. Views where the point is
occluded (ray-traced against the current mesh estimate) or seen too obliquely are left out.

**3-D snap** (:func:`snap`): "searches in a small 3D neighborhood to find the location that
yields the best dot-strength" — vectorised over many points at once: a ball of candidate
offsets (``radius``, spacing ``step``) about each start, then a finer ball (spacing
``step / 3``) about the best; finally each view's sub-pixel peak of the strength map next to
the point's projection is triangulated (:mod:`mifacerf.geometry.triangulate`), which gives the point to a
fraction of a pixel. A point counts as snapped only when at least two views agree (the
triangulation's worst reprojection error is below ``max_reproj`` pixels).

**Progressive snap** (:func:`progressive_snap`), as in the paper:

1. ``S`` = the known points (the coarse points, themselves snapped from the user's position);
2. their offsets = known position − morph prediction;
3. threshold = the strongest dot strength of the known points;
4. for every point bordering ``S``: predicted offset from its neighbours in ``S`` (the paper
   averages their offsets; here a local affine map fitted to the snapped points within two rings,
   which also carries a rotation or a stretch, :func:`predict_from_neighbours`); snap from the
   prediction + offset; accept (add to ``S``) if the strength is at least the threshold;
5. repeat 4 while points are added;
6. lower the threshold (× ``decay``); while it stays above ``floor`` × the initial threshold
   (and above ``min_strength``), go to 4.

Dots never reached stay at their prediction (+ the neighbours' mean offset) and are
reported as not registered (status 0).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from .dots import bilinear, peak_near
from ..geometry.triangulate import triangulate


def ball(radius: float, step: float) -> np.ndarray:
    """Offsets (K, 3) of a cubic grid with spacing ``step`` inside a ball of ``radius`` (origin first)."""
    n = int(np.floor(radius / step + 1e-9))
    g = np.arange(-n, n + 1) * step
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    P = P[np.linalg.norm(P, axis=1) <= radius + 1e-12]
    return P[np.argsort(np.linalg.norm(P, axis=1), kind="stable")]


def view_weights(vis: np.ndarray, cosines: np.ndarray, floor: float = 0.35) -> np.ndarray:
    """(C, M) weights of the views in the dot strength: ``1 / max(cos, floor)`` where visible, else 0.

    A round dot seen at an angle θ from its normal covers ``cos θ`` of its frontal area, and the
    matched filter answers in proportion; dividing by the expected foreshortening puts an oblique but
    clearly present dot on the same scale as a frontal one (``floor`` bounds the gain)."""
    return np.where(vis, 1.0 / np.maximum(np.nan_to_num(cosines, nan=1.0), floor), 0.0)


class Views:
    """The dot-strength maps of one expression: ``cams`` (C cameras), ``maps`` (C, H, W)."""

    def __init__(self, cams: list[Camera], maps, centroid_sigma: float | None = None):
        self.cams = list(cams)
        self.maps = [np.asarray(m, np.float32) for m in maps]
        self.centroid_sigma = centroid_sigma

    def per_view(self, X: np.ndarray) -> np.ndarray:
        """(C, M) strength of points X (M, 3) in each view (0 outside the image)."""
        out = np.zeros((len(self.cams), len(X)))
        for c, (cam, m) in enumerate(zip(self.cams, self.maps)):
            uv, _ = cam.project(X)
            out[c] = bilinear(m, uv)
        return out

    def strength(self, X: np.ndarray, vis: np.ndarray) -> np.ndarray:
        """(M,) dot strength: the sum over the views where each point is visible (``vis`` (C, M), bool,
        or float view weights, 0 where not visible)."""
        return (self.per_view(X) * vis).sum(0)


@dataclass
class SnapResult:
    """``X`` (M, 3) snapped positions; ``strength`` (M,); ``n_views`` (M,) views that agreed;
    ``ok`` (M,) triangulated from ≥ 2 agreeing views; ``reproj`` (M,) worst reprojection error (px)."""

    X: np.ndarray
    strength: np.ndarray
    n_views: np.ndarray
    ok: np.ndarray
    reproj: np.ndarray


def _grid_search(views: Views, X0: np.ndarray, vis: np.ndarray, offsets: np.ndarray, chunk: int,
                 penalty: np.ndarray | None = None) -> np.ndarray:
    best = np.empty_like(X0)
    K = len(offsets)
    for s in range(0, len(X0), chunk):
        x = X0[s:s + chunk]
        cand = (x[:, None, :] + offsets[None]).reshape(-1, 3)
        v = np.repeat(vis[:, s:s + chunk], K, axis=1)
        st = views.strength(cand, v).reshape(len(x), K)
        if penalty is not None:
            st = st - penalty[None]
        k = np.argmax(st, axis=1)        # ties: the smallest offset (offsets sorted by length)
        best[s:s + chunk] = x + offsets[k]
    return best


def snap(views: Views, X0: np.ndarray, vis: np.ndarray, radius: float, step: float,
         max_reproj: float = 1.0, min_view_strength: float = 0.25, chunk: int = 256,
         prior: float = 0.4, two_view_max_px: float | None = 2.0,
         two_view_max_shift: float | None = None) -> SnapResult:
    """3-D snap of points ``X0`` (M, 3) with visibility ``vis`` (C, M); see the module docstring.

    ``vis`` may hold float weights per view (0 = not visible): :func:`view_weights` compensates the
    foreshortening of dots seen obliquely.

    ``prior``: the coarse search maximises ``strength − prior · (|offset| / radius)²``, a mild
    preference for the predicted position that settles two-view ambiguities (a wrong pair of
    dots on corresponding epipolar lines) in favour of the nearer candidate; ``two_view_max_px``:
    a point found in only two views must project within this many pixels of its start in both
    (the third view that would expose a phantom is missing); ``two_view_max_shift`` (metres): and lie
    this near its start in 3-D (a wrong dot in one oblique view and the right one in the other meet at
    a point shifted in depth, which the image-space tests barely see; None where the start's depth is
    itself uncertain, as for points a user clicked in two views).
    """
    X0 = np.asarray(X0, np.float64).reshape(-1, 3)
    M = len(X0)
    if M == 0:
        z = np.zeros(0)
        return SnapResult(np.zeros((0, 3)), z, z.astype(int), z.astype(bool), z)
    w = np.asarray(vis, np.float64).reshape(len(views.cams), M)
    vis = w > 0
    offs = ball(radius, step)
    Xc = _grid_search(views, X0, w, offs, chunk, prior * (np.linalg.norm(offs, axis=1) / radius) ** 2)
    Xf = _grid_search(views, Xc, w, ball(step, step / 3.0), chunk)
    # sub-pixel: per-view peaks next to the projection, triangulated
    C = len(views.cams)
    uv = np.full((C, M, 2), np.nan)
    for c, (cam, m) in enumerate(zip(views.cams, views.maps)):
        sel = np.flatnonzero(vis[c])
        if sel.size == 0:
            continue
        p, _ = cam.project(Xf[sel])
        pk, val = peak_near(m, p, 1.0, views.centroid_sigma)
        good = (val >= min_view_strength) & (np.linalg.norm(pk - p, axis=1) <= 1.5)
        uv[c, sel[good]] = pk[good]
    tr = triangulate(views.cams, uv, max_error=max_reproj)
    ok = tr.ok & (tr.max_error <= max_reproj)
    # the refined point must still look like the grid's answer in every view it uses (an image-space
    # test: two views with a short baseline may move it in depth by more than a grid step)
    Xt = np.where(ok[:, None], tr.points, Xf)
    for c, cam in enumerate(views.cams):
        m = tr.used[c] & ok
        if m.any():
            shift = np.linalg.norm(cam.project(Xt[m])[0] - cam.project(Xf[m])[0], axis=1)
            ok[np.flatnonzero(m)[shift > 1.5]] = False
    # two views alone can agree on a phantom (any two dots on corresponding epipolar lines): a
    # two-view answer must stay near the start in both images (and in 3-D)
    two = ok & (tr.n_views == 2)
    if two_view_max_shift is not None:
        ok &= ~(two & (np.linalg.norm(np.nan_to_num(tr.points, nan=1e9) - X0, axis=1) > two_view_max_shift))
        two &= ok
    if two.any() and two_view_max_px is not None:
        for c, cam in enumerate(views.cams):
            m = two & tr.used[c]
            if m.any():
                shift = np.linalg.norm(cam.project(tr.points[m])[0] - cam.project(X0[m])[0], axis=1)
                ok[np.flatnonzero(m)[shift > two_view_max_px]] = False
    X = np.where(ok[:, None], tr.points, Xf)
    strength = views.strength(X, w)
    return SnapResult(X, strength, np.where(ok, tr.n_views, 0), ok, np.where(ok, tr.max_error, np.nan))


# --------------------------------------------------------------------------------- progressive snap
def dot_graph(n_vertices: int, triangles: np.ndarray, is_dot: np.ndarray) -> list[np.ndarray]:
    """Neighbours of each vertex among the dot vertices: joined by an edge, or through one non-dot vertex."""
    import scipy.sparse as sp

    from ..geometry.graph import edge_graph

    A = edge_graph(np.asarray(triangles, np.int64).reshape(-1, 3), n_vertices).astype(np.float64)
    nd = sp.diags((~np.asarray(is_dot)).astype(float))
    A2 = A + A @ nd @ A
    A2 = A2.tocsr()
    A2.setdiag(0)
    A2.eliminate_zeros()
    dmask = np.asarray(is_dot)
    out = []
    for v in range(n_vertices):
        nb = A2.indices[A2.indptr[v]:A2.indptr[v + 1]]
        out.append(nb[dmask[nb]])
    return out


@dataclass
class ProgressiveResult:
    """``X`` (T, 3) positions (snapped dots, known points, the rest predicted + offset);
    ``snapped`` (T,) bool; ``strength`` (T,) at the final position (NaN if never tried);
    ``level`` (T,) the threshold step at which each point was accepted (-1 known, -2 never);
    ``schedule`` the thresholds used; ``attempts`` total snap operations."""

    X: np.ndarray
    snapped: np.ndarray
    strength: np.ndarray
    level: np.ndarray
    schedule: list = field(default_factory=list)
    attempts: int = 0
    accepted_per_level: list = field(default_factory=list)


def _scatter(n: int, ids: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.full((n, values.shape[1]), np.nan)
    out[ids] = values
    return out


def _exclusive(acc: np.ndarray, cand_X: np.ndarray, taken: np.ndarray, X: np.ndarray, starts: np.ndarray,
               min_separation: float) -> np.ndarray:
    """Drop accepted candidates that landed on a dot already taken (by a point of ``S`` or by another
    candidate nearer its start): one image dot registers one template point."""
    if acc.size == 0 or min_separation <= 0:
        return acc
    from scipy.spatial import cKDTree

    P = cand_X[acc]
    keep = np.ones(len(acc), bool)
    if taken.size:
        d, _ = cKDTree(X[taken]).query(P)
        keep &= d > min_separation
    # among the candidates: the one nearest its own start wins
    dist_start = np.linalg.norm(P - starts, axis=1)
    for i, j in cKDTree(P).query_pairs(min_separation):
        if dist_start[i] <= dist_start[j]:
            keep[j] = False
        else:
            keep[i] = False
    return acc[keep]


def two_rings(neighbours: list[np.ndarray]) -> list[np.ndarray]:
    """Per vertex, the ids within two steps of the dot graph (``neighbours`` from :func:`dot_graph`)."""
    return [np.unique(np.concatenate([nb] + [neighbours[u] for u in nb])) if len(nb) else nb for nb in neighbours]


def predict_from_neighbours(pred, X, in_S, ids, neighbours, rings2, max_anchors: int = 12) -> np.ndarray:
    """Start positions of points ``ids``: their prediction corrected by the snapped points round them.

    The paper averages the neighbours' offsets; here the snapped points within two rings give a
    weighted local affine map (regularised towards rigid, :func:`mifacerf.geometry.schaefer2006.local_affine`) from
    predicted to snapped positions, so a rotating or stretching region (a jaw opening) carries its
    first-order motion to the next point, not only its mean translation. With fewer than three
    such points, the mean offset of the snapped neighbours (the paper's rule).
    """
    from ..geometry.schaefer2006 import local_affine

    M = len(ids)
    src = np.zeros((M, max_anchors, 3))
    dst = np.zeros((M, max_anchors, 3))
    w = np.zeros((M, max_anchors))
    for k, v in enumerate(ids):
        a = rings2[v][in_S[rings2[v]]]
        if len(a) < 3:
            a = neighbours[v][in_S[neighbours[v]]]
        if len(a) == 0:
            continue
        d = np.linalg.norm(pred[a] - pred[v], axis=1)
        o = np.argsort(d)[:max_anchors]
        a, d = a[o], d[o]
        src[k, :len(a)], dst[k, :len(a)] = pred[a], X[a]
        w[k, :len(a)] = 1.0 / (d + 0.003) ** 2
    return local_affine(src, dst, w, pred[ids])


def progressive_snap(views: Views, pred: np.ndarray, dots: np.ndarray, neighbours: list[np.ndarray],
                     known: dict, vis: np.ndarray, radius: float, step: float, decay: float = 0.8,
                     floor: float = 0.1, min_strength: float = 0.8, max_reproj: float = 1.0,
                     known_radius: float | None = None, min_separation: float = 0.0,
                     two_view_max_shift: float | None = None, dot_holders=None) -> ProgressiveResult:
    """The paper's progressive snap (module docstring).

    ``pred`` (T, 3) morph predictions of all template vertices; ``dots`` ids to register;
    ``neighbours`` per vertex its dot neighbours (:func:`dot_graph`); ``known`` {vertex id: (3,)}
    known positions (coarse points); ``vis`` (C, T) visibility from the current mesh estimate.
    ``radius`` / ``step`` of the 3-D search (metres); ``known_radius`` the search about a known
    point (default ``radius / 2``); ``min_separation`` (metres): a snap landing closer than this to
    a point already registered is refused (it found that point's dot, not its own);
    ``two_view_max_shift``: see :func:`snap`; ``dot_holders``: ids of the points that hold an image dot once
    registered or known (default ``dots``): a known fiducial that is not snapped again (a refit round's
    registered ones) still takes its dot.
    """
    pred = np.asarray(pred, np.float64)
    T = len(pred)
    X = pred.copy()
    offset = np.full((T, 3), np.nan)
    in_S = np.zeros(T, bool)
    snapped = np.zeros(T, bool)
    strength = np.full(T, np.nan)
    level = np.full(T, -2, np.int64)
    is_target = np.zeros(T, bool)
    is_target[np.asarray(dots, np.int64)] = True
    holds = is_target.copy()
    if dot_holders is not None:
        holds[np.asarray(dot_holders, np.int64)] = True
    attempts = 0

    # 1-2. known points, snapped when they are dots
    kid = np.array(sorted(known), np.int64)
    if kid.size:
        KX = np.stack([np.asarray(known[k], np.float64) for k in kid])
        kd = kid[is_target[kid]]
        X[kid] = KX
        if kd.size:
            r = snap(views, KX[is_target[kid]], vis[:, kd], known_radius or radius / 2, step, max_reproj)
            attempts += len(kd)
            X[kd[r.ok]] = r.X[r.ok]
            snapped[kd[r.ok]] = True
            strength[kd] = r.strength
        in_S[kid] = True
        level[kid] = -1
        offset[kid] = X[kid] - pred[kid]
    # 3. initial threshold
    ks = strength[kid[snapped[kid]]] if kid.size else np.zeros(0)
    if ks.size:
        t0 = float(np.max(ks))
    else:  # no known dot: start from the strongest dot found from the predictions
        r = snap(views, pred[is_target], vis[:, is_target], radius, step, max_reproj)
        attempts += int(is_target.sum())
        t0 = float(np.max(np.where(r.ok, r.strength, 0.0), initial=0.0)) or float(len(views.cams))
    t_floor = max(floor * t0, min_strength)
    rings2 = two_rings(neighbours)
    schedule = []
    last_start = np.full((T, 3), np.nan)
    cache_X = np.full((T, 3), np.nan)
    cache_s = np.full(T, -np.inf)
    cache_ok = np.zeros(T, bool)
    accepted_per_level = []
    t = t0
    lev = 0
    while True:
        schedule.append(t)
        n_acc = 0
        while True:
            if in_S.any():
                border = np.array([v for v in np.flatnonzero(is_target & ~in_S)
                                   if in_S[neighbours[v]].any()], np.int64)
            else:   # nothing known: seed with the strongest dots found from their predictions
                border = np.flatnonzero(is_target)
            if border.size == 0:
                break
            start = predict_from_neighbours(pred, X, in_S, border, neighbours, rings2)
            redo = ~(np.linalg.norm(start - last_start[border], axis=1) < 0.1 * step)
            if redo.any():
                rb = border[redo]
                r = snap(views, start[redo], vis[:, rb], radius, step, max_reproj,
                         two_view_max_shift=two_view_max_shift)
                attempts += len(rb)
                last_start[rb] = start[redo]
                cache_X[rb], cache_s[rb], cache_ok[rb] = r.X, r.strength, r.ok
            acc = border[cache_ok[border] & (cache_s[border] >= t)]
            acc = _exclusive(acc, cache_X, np.flatnonzero(in_S & holds), X, start[np.searchsorted(border, acc)]
                             if acc.size else np.zeros((0, 3)), min_separation)
            X[border] = np.where(cache_ok[border, None], cache_X[border], start)
            strength[border] = cache_s[border]
            if acc.size == 0:
                break
            in_S[acc] = True
            snapped[acc] = True
            level[acc] = lev
            offset[acc] = X[acc] - pred[acc]
            n_acc += len(acc)
        accepted_per_level.append(n_acc)
        t *= decay
        lev += 1
        if t < t_floor * (1 - 1e-9):
            break
    # points never reached by propagation: one last try from distance-weighted offsets
    rest = np.flatnonzero(is_target & ~in_S)
    if rest.size and in_S.any():
        sid = np.flatnonzero(in_S)
        d = np.linalg.norm(pred[rest, None] - pred[None, sid], axis=-1)
        w = 1.0 / (d + 1e-3) ** 2
        off = (w @ offset[sid]) / w.sum(1, keepdims=True)
        start = pred[rest] + off
        r = snap(views, start, vis[:, rest], radius, step, max_reproj, two_view_max_shift=two_view_max_shift)
        attempts += len(rest)
        acc = r.ok & (r.strength >= t_floor)
        a_ids = _exclusive(rest[acc], _scatter(T, rest, r.X), np.flatnonzero(in_S & holds), X, start[acc],
                           min_separation)
        acc = np.isin(rest, a_ids)
        X[rest] = np.where(acc[:, None], r.X, start)
        strength[rest] = r.strength
        snapped[rest[acc]] = True
        level[rest[acc]] = lev
        accepted_per_level.append(int(acc.sum()))
    return ProgressiveResult(X, snapped, strength, level, schedule, attempts, accepted_per_level)
