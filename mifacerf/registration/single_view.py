"""Fiducials that only one camera sees: the 3-D snap with a single view (beyond the paper's ≥ 2 views).

The paper's 3-D snap maximises the dot strength summed over the views that see a point; with one
view that sum is constant along the camera ray, so the data fix the point's position across the
ray but not its depth. :func:`single_view_snap` takes each point that shows as a dot in exactly one
of the views that see it — the free dot peak near the projection of the point's current estimate (the
morph prediction corrected by its registered neighbours) — and places the point on that peak's ray
at the depth nearest to the estimate: the image position from the data, the depth from the
surface. Such points are registered, and reported as single-view (their depth error is the
estimate's, not a triangulation's).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera


@dataclass
class SingleViewResult:
    """``points`` (K,) indices into the estimates given; ``X`` (K, 3) world positions; ``view`` (K,) the camera
    index that saw each; ``uv`` (K, 2) the dot's peak there (pixels); ``shift_px`` (K,) peak − projection."""

    points: np.ndarray
    X: np.ndarray
    view: np.ndarray
    uv: np.ndarray
    shift_px: np.ndarray


def single_view_snap(cams: list[Camera], peaks: list, free: list[np.ndarray], X0: np.ndarray, visible: np.ndarray,
                     search_px: float, min_value: float) -> SingleViewResult:
    """Place points ``X0`` (M, 3) (world, metres) that show as a dot in exactly one of the views ``visible``
    (C, M) bool says see them (a dot hidden in a view by something the mesh does not model — hair, a lid —
    leaves one view).

    ``peaks``: per view, :class:`.consensus.Peaks` (sub-pixel dot peaks and their strengths); ``free``: per view
    (N_c,) bool, peaks not already taken by a registered point. In each view a point claims the free peak of
    at least ``min_value`` nearest to its projection, within ``search_px`` pixels; a peak claimed by two
    points goes to the nearer one. A point with a claim in exactly one view is placed; with claims in two or
    more views it is left alone (the views would have to agree: the multi-view snap's business).
    """
    from scipy.spatial import cKDTree

    X0 = np.asarray(X0, np.float64).reshape(-1, 3)
    M = len(X0)
    visible = np.asarray(visible, bool).reshape(len(cams), M)
    claim = np.full((len(cams), M), -1, np.int64)          # peak index per (view, point)
    dist = np.full((len(cams), M), np.inf)
    cands = []
    for c, cam in enumerate(cams):
        ok_peak = np.asarray(free[c], bool) & (np.asarray(peaks[c].value) >= min_value)
        cand = peaks[c].uv[ok_peak]
        cands.append(cand)
        ids = np.flatnonzero(visible[c])
        if ids.size == 0 or len(cand) == 0:
            continue
        p, _ = cam.project(X0[ids])
        good = np.isfinite(p).all(1)
        ids, p = ids[good], p[good]
        if ids.size == 0:
            continue
        d, k = cKDTree(cand).query(p, distance_upper_bound=search_px)
        hit = np.isfinite(d)
        ids, d, k = ids[hit], d[hit], k[hit]
        order = np.argsort(d, kind="stable")               # one peak, one point: the nearest claimant
        _, first = np.unique(k[order], return_index=True)
        keep = order[first]
        claim[c, ids[keep]] = k[keep]
        dist[c, ids[keep]] = d[keep]
    one = np.flatnonzero((claim >= 0).sum(0) == 1)
    if one.size == 0:
        z = np.zeros(0)
        return SingleViewResult(z.astype(np.int64), np.zeros((0, 3)), z.astype(np.int64), np.zeros((0, 2)), z)
    view = np.argmax(claim[:, one] >= 0, axis=0)
    X = np.empty((len(one), 3))
    uv = np.empty((len(one), 2))
    for c in np.unique(view):
        sel = np.flatnonzero(view == c)
        uv[sel] = cands[c][claim[c, one[sel]]]
        origin, ray = cams[c].pixel_rays(uv[sel])
        t = ((X0[one[sel]] - origin) * ray).sum(1)
        X[sel] = origin + t[:, None] * ray
    return SingleViewResult(one, X, view, uv, dist[view, one])
