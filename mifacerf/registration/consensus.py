"""Image-space consensus snap: the last pass over the fiducials the progressive 3-D snap left out.

The 3-D snap (:mod:`.snap`) maximises the *summed* dot strength over a small ball about a
prediction. A few kinds of dots defeat it:

* the prediction is further off than the ball — typically a dot the user clicked in two nearby views
  of the neutral (its depth is uncertain by several millimetres, its image positions by a pixel or
  two), and every later expression morphed from that position;
* an oblique view sees a *neighbouring* dot inside the ball (foreshortening packs the dots together)
  and its strength, divided by the foreshortening, outweighs the faint true dot in the other views;
* the dot is faint everywhere (under an eyebrow, at grazing angles).

This pass works in the images instead, with every registered dot's image accounted for:

1. the dots of every view are its strength map's local maxima (sub-pixel centroids, :func:`view_peaks`);
   a peak within ``taken_px`` of the projection of a registered fiducial visible in that view belongs
   to that fiducial and is *taken* (one image dot, one template point, :func:`free_peaks`);
2. for a point left out, every pair of views that should see it and every pair of free peaks within
   ``search_px`` of its projected start give a hypothesis, triangulated; a pair whose rays miss each
   other by more than ``max_reproj`` pixels is none (epipolar consistency); each hypothesis then collects
   the free peak nearest its projection in every other view that should see it (:func:`hypotheses`);
3. a hypothesis is credible when its second-strongest peak reaches ``two_view_strength`` and — seen by two
   views only — they agree to ``two_view_reproj`` (the peaks are centroids good to a tenth of a pixel; a
   looser match is a chance alignment of two different dots);
4. the credible hypothesis seen by the most views wins; among equals, the nearest the start if the next
   is at least twice as far, else the point is ambiguous and left. The winner must lie within
   ``max_shift`` of the start, and, when its second-strongest peak is fainter than ``strong``, within
   ``weak_shift``: a faint dot is believed only where the registered neighbours put it;
5. one image dot, one point: a winner using a peak that another point's hypotheses also use is kept only
   if it has more views, or a start much nearer (half the distance); two winners on one dot are both left.

:meth:`.register.Registrar.consensus_pass` runs it with growing ``max_shift`` and repeats each step while
points join (each one registered improves its neighbours' starts and takes its own image dots). Points
that pass are triangulated from the agreeing peaks (a fraction of a pixel, like the 3-D snap's
refinement); everything else stays unregistered (status 0).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera
from .dots import peak_near
from ..geometry.maxima import local_maxima
from ..geometry.triangulate import triangulate


@dataclass
class Peaks:
    """The dots of one view: ``uv`` (N, 2) sub-pixel positions, ``value`` (N,) strength."""

    uv: np.ndarray
    value: np.ndarray

    def tree(self):
        from scipy.spatial import cKDTree

        return cKDTree(self.uv if len(self.uv) else np.zeros((0, 2)))


def view_peaks(strength_map: np.ndarray, min_value: float, centroid_sigma: float | None = None) -> Peaks:
    """Local maxima (3 × 3) of a strength map at least ``min_value``, refined to sub-pixel centroids."""
    m = np.asarray(strength_map, np.float32)
    mx = local_maxima(m, min_value, positive=True)
    ij = np.argwhere(mx)
    if len(ij) == 0:
        return Peaks(np.zeros((0, 2)), np.zeros(0))
    uv0 = ij[:, ::-1].astype(np.float64)
    uv, val = peak_near(m, uv0, 0.0, centroid_sigma)
    ok = np.isfinite(uv).all(1)
    uv, val = uv[ok], val[ok]
    # plateaus give several maxima for one dot: keep the strongest of those within half a pixel
    order = np.argsort(-val)
    uv, val = uv[order], val[order]
    from scipy.spatial import cKDTree

    keep = np.ones(len(uv), bool)
    for i, j in sorted(cKDTree(uv).query_pairs(0.5)):
        if keep[i] and keep[j]:
            keep[j] = False
    return Peaks(uv[keep], val[keep])


def free_peaks(peaks: list[Peaks], cams: list[Camera], X: np.ndarray, visible: np.ndarray,
               taken_px: float) -> list[np.ndarray]:
    """Per view, (N,) bool: peaks not within ``taken_px`` of a registered point ``X`` (M, 3) visible
    there (``visible`` (C, M) bool)."""
    out = []
    for c, (pk, cam) in enumerate(zip(peaks, cams)):
        free = np.ones(len(pk.uv), bool)
        sel = np.flatnonzero(visible[c])
        if len(pk.uv) and sel.size:
            uv, _ = cam.project(X[sel])
            uv = uv[np.isfinite(uv).all(1)]
            if len(uv):
                from scipy.spatial import cKDTree

                d, _ = cKDTree(uv).query(pk.uv)
                free = d > taken_px
        out.append(free)
    return out


@dataclass
class Hypothesis:
    point: int          #: index of the point (into the arrays given to :func:`hypotheses`)
    X: np.ndarray       #: (3,) triangulated position
    views: np.ndarray   #: (C,) bool, the views whose peaks agree
    strength: np.ndarray  #: (C,) peak strength in those views (0 elsewhere)
    reproj: float       #: worst reprojection error (pixels)
    peak_ids: np.ndarray  #: (C,) index of the agreeing peak in each view (-1: none)


def hypotheses(cams: list[Camera], peaks: list[Peaks], free: list[np.ndarray], X0: np.ndarray,
               vis: np.ndarray, search_px: float = 4.0, support_px: float = 1.0,
               max_reproj: float = 1.0) -> list[list[Hypothesis]]:
    """Every consistent hypothesis per point (``X0`` (M, 3) starts, ``vis`` (C, M) views that should see
    each point): pairs of free peaks within ``search_px`` of the projected start in two views, triangulated,
    kept if their worst reprojection error is at most ``max_reproj``, then extended by the free peak within
    ``support_px`` of the projection in every other view of ``vis`` (re-triangulated; views that disagree
    by more than ``max_reproj`` dropped). Duplicates (same peaks) are merged."""
    C, M = vis.shape
    trees = [pk.tree() for pk in peaks]
    cand = [[np.zeros(0, np.int64)] * M for _ in range(C)]
    for c, cam in enumerate(cams):
        sel = np.flatnonzero(vis[c])
        if sel.size == 0 or len(peaks[c].uv) == 0:
            continue
        uv, _ = cam.project(X0[sel])
        for i, p in zip(sel, uv):
            if np.isfinite(p).all():
                idx = np.asarray(trees[c].query_ball_point(p, search_px), np.int64)
                cand[c][i] = idx[free[c][idx]] if idx.size else idx
    # pairs
    pts, obs = [], []
    for i in range(M):
        vs = [c for c in range(C) if vis[c, i] and cand[c][i].size]
        for a in range(len(vs)):
            for b in range(a + 1, len(vs)):
                ca, cb = vs[a], vs[b]
                for pa in cand[ca][i]:
                    for pb in cand[cb][i]:
                        pts.append(i)
                        obs.append((ca, pa, cb, pb))
    out: list[list[Hypothesis]] = [[] for _ in range(M)]
    if not pts:
        return out
    pts = np.asarray(pts, np.int64)
    N = len(pts)
    uv = np.full((C, N, 2), np.nan)
    pid = np.full((C, N), -1, np.int64)
    for n, (ca, pa, cb, pb) in enumerate(obs):
        uv[ca, n], uv[cb, n] = peaks[ca].uv[pa], peaks[cb].uv[pb]
        pid[ca, n], pid[cb, n] = pa, pb
    tr = triangulate(cams, uv)
    good = tr.ok & (tr.max_error <= max_reproj)
    pts, uv, pid, Xp = pts[good], uv[:, good], pid[:, good], tr.points[good]
    if len(pts) == 0:
        return out
    # support from the other views
    for c, cam in enumerate(cams):
        if len(peaks[c].uv) == 0:
            continue
        need = vis[c, pts] & (pid[c] < 0)
        if not need.any():
            continue
        p, _ = cam.project(Xp[need])
        d, k = trees[c].query(np.nan_to_num(p, nan=-1e6))
        ok = (d <= support_px) & free[c][np.minimum(k, len(peaks[c].uv) - 1)]
        n_idx = np.flatnonzero(need)[ok]
        uv[c, n_idx] = peaks[c].uv[k[ok]]
        pid[c, n_idx] = k[ok]
    tr = triangulate(cams, uv, max_error=max_reproj)
    good = tr.ok & (tr.max_error <= max_reproj)
    seen = set()
    for n in np.flatnonzero(good):
        used = tr.used[:, n]
        key = (int(pts[n]),) + tuple(int(pid[c, n]) if used[c] else -1 for c in range(C))
        if key in seen:
            continue
        seen.add(key)
        st = np.zeros(C)
        for c in np.flatnonzero(used):
            st[c] = peaks[c].value[pid[c, n]]
        ids = np.where(used, pid[:, n], -1)
        out[pts[n]].append(Hypothesis(int(pts[n]), tr.points[n], used.copy(), st, float(tr.max_error[n]), ids))
    return out


def _merge(hs: list[Hypothesis], radius: float) -> list[Hypothesis]:
    """One hypothesis per image dot: of those within ``radius`` (metres) of each other, the one seen by the
    most views (then the strongest)."""
    hs = sorted(hs, key=lambda h: (-int(h.views.sum()), -float(h.strength.sum())))
    out: list[Hypothesis] = []
    for h in hs:
        if all(np.linalg.norm(h.X - g.X) > radius for g in out):
            out.append(h)
    return out


@dataclass
class ConsensusResult:
    """``accepted`` (K,) indices into the points given; ``X`` (K, 3); ``n_views`` (K,); ``reproj`` (K,);
    ``rejected`` {reason: count} over the points left."""

    accepted: np.ndarray
    X: np.ndarray
    n_views: np.ndarray
    reproj: np.ndarray
    rejected: dict


def consensus_snap(cams: list[Camera], peaks: list[Peaks], free: list[np.ndarray], X0: np.ndarray,
                   vis: np.ndarray, taken_X: np.ndarray, *, max_shift: float, weak_shift: float,
                   search_px: float = 5.0, support_px: float = 1.0, max_reproj: float = 1.0,
                   two_view_reproj: float = 0.3, two_view_strength: float = 0.2, strong: float = 0.5,
                   merge_radius: float = 0.002, min_separation: float = 0.002) -> ConsensusResult:
    """The decision of the module docstring for points starting at ``X0`` (M, 3) with views ``vis`` (C, M)
    (bool); ``taken_X`` (K, 3) the registered points (a hypothesis within ``min_separation`` of one is
    refused).

    A hypothesis counts when its views agree to ``max_reproj`` pixels — two views alone to
    ``two_view_reproj`` (their peaks are centroids good to a tenth of a pixel; a looser match is a chance
    alignment of two different dots) and with both peaks at least ``two_view_strength``. Of those, the one
    seen by the most views is taken, or, among equals, the nearest to the start if the next is at least
    twice as far; otherwise the point is ambiguous. The chosen one must lie within ``max_shift`` (metres)
    of the start, and a two-view one with a peak weaker than ``strong`` within ``weak_shift``: a faint pair
    is believed only where the registered neighbours put the dot.
    """
    M = len(X0)
    H = hypotheses(cams, peaks, free, X0, vis, search_px, support_px, max_reproj)
    from scipy.spatial import cKDTree

    tree = cKDTree(taken_X) if len(taken_X) else None
    rejected: dict = {}

    def reject(why):
        rejected[why] = rejected.get(why, 0) + 1

    def core(h):   # the second-strongest peak: the weaker of the two best views
        return float(np.sort(h.strength[h.views])[-2])

    def credible(h):
        if core(h) < two_view_strength:
            return False
        return h.views.sum() >= 3 or h.reproj <= two_view_reproj

    best: dict[int, Hypothesis] = {}
    merged_all: dict[int, list[Hypothesis]] = {}
    for i in range(M):
        hs = [h for h in H[i] if credible(h)]
        if tree is not None:
            hs = [h for h in hs if tree.query(h.X)[0] > min_separation]
        hs = _merge(hs, merge_radius)
        merged_all[i] = hs
        if not hs:
            reject("no consistent dots")
            continue
        nv = np.array([int(h.views.sum()) for h in hs])
        top = [h for h, n in zip(hs, nv) if n == nv.max()]
        d = sorted((float(np.linalg.norm(h.X - X0[i])), k) for k, h in enumerate(top))
        if len(d) > 1 and d[0][0] > 0.5 * d[1][0]:
            reject("ambiguous (several consistent dots)")
            continue
        h = top[d[0][1]]
        if d[0][0] > max_shift:
            reject("too far from the prediction")
            continue
        if core(h) < strong and d[0][0] > weak_shift:
            reject("faint dots away from the prediction")
            continue
        best[i] = h
    # one image dot, one point: a peak another point's hypotheses also use goes to the hypothesis with more
    # views, then to the point whose start is much nearer; otherwise to nobody
    users: dict = {}
    for i, hs in merged_all.items():
        for h in hs:
            for c in np.flatnonzero(h.views):
                users.setdefault((int(c), int(h.peak_ids[c])), []).append((i, h))
    drop = set()
    for i, h in best.items():
        di = np.linalg.norm(h.X - X0[i])
        for c in np.flatnonzero(h.views):
            for j, g in users.get((int(c), int(h.peak_ids[c])), []):
                if j == i:
                    continue
                ni, nj = int(h.views.sum()), int(g.views.sum())
                if ni > nj or (ni == nj and di < 0.5 * np.linalg.norm(g.X - X0[j])):
                    continue
                drop.add(i)
    for _ in drop:
        reject("its dots are claimed by another point")
    acc = [i for i in sorted(best) if i not in drop]
    if len(acc) > 1:   # two points on one dot through different peaks: neither
        P = np.array([best[i].X for i in acc])
        bad = set()
        for a, b in cKDTree(P).query_pairs(min_separation):
            bad.update((acc[a], acc[b]))
        for _ in bad:
            reject("two points on one dot")
        acc = [i for i in acc if i not in bad]
    acc = np.asarray(acc, np.int64)
    return ConsensusResult(acc, np.array([best[i].X for i in acc]).reshape(-1, 3),
                           np.array([int(best[i].views.sum()) for i in acc], np.int64),
                           np.array([best[i].reproj for i in acc]), rejected)
