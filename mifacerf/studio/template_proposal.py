"""A template proposed from the neutral's images alone (beyond the paper, whose user spent ~1 h on it).

1. **Dots in every view**: the dot-strength map of the neutral's diffuse proxy under the prior filter
   (:func:`.proposals.untuned_filter`: yellow made orthogonal to the skin colour; no template exists yet),
   its local maxima at least ``min_peak`` refined to sub-pixel centroids (:func:`~mifacerf.registration.consensus.view_peaks`).
2. **Matched across views by epipolar geometry**: for every pair of cameras, every pair of peaks whose
   rays pass within ``epipolar_px`` of each other (the distance of one peak from the other's epipolar
   line, through the calibrated, distorted cameras) is triangulated; each hypothesis collects the
   nearest peak within ``support_px`` of its projection in every other view and is triangulated again
   from all of them. Hypotheses are taken best first (most views, then smallest reprojection error),
   one image dot for one 3-D point; a two-view hypothesis is taken only where neither of its peaks has
   another candidate (two views can agree on a phantom).
3. **Connected by a surface triangulation**: Delaunay in (azimuth, height) about the vertical axis, as
   seen from in front (:func:`~mifacerf.registration.hand.auto_coarse_triangles`' projection), without
   the long hull edges.
4. **Coarse points**: ``n_coarse`` fiducials spread over the face (farthest-point sampling from the
   one nearest the centre), with their Delaunay mesh.

Not proposed (the user adds them; registration flags what is missing): the lip and eyelid margins,
the eyes, the teeth, the ear and nose-bridge points, the regions. Every vertex is a ``dot``.
"""
from __future__ import annotations

import numpy as np

from ..geometry.footprint import centre_footprint
from ..geometry.triangulate import triangulate
from ..registration.consensus import view_peaks
from ..registration.hand import DEFAULT_DOT_RADIUS, TEMPLATE_SCHEMA, auto_coarse_triangles


def _epipolar_pairs(ca, cb, ua: np.ndarray, ub: np.ndarray, tol_px: float) -> np.ndarray:
    """(n, 2) index pairs (i into ua, j into ub) whose rays pass within ``tol_px`` (in b's pixels)."""
    xa = ca.undistort_pixels(ua)
    xb = cb.undistort_pixels(ub)
    R = cb.R @ ca.R.T                 # a's camera frame -> b's
    t = cb.t - R @ ca.t
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    E = tx @ R
    ha = np.concatenate([xa, np.ones((len(xa), 1))], 1)
    hb = np.concatenate([xb, np.ones((len(xb), 1))], 1)
    lines = ha @ E.T                  # epipolar lines in b (normalised coordinates)
    num = np.abs(hb @ lines.T)        # (nb, na)
    den = np.linalg.norm(lines[:, :2], axis=1)[None]
    d_px = num / np.maximum(den, 1e-12) * np.sqrt(cb.K[0, 0] * cb.K[1, 1])
    j, i = np.nonzero(d_px < tol_px)
    return np.stack([i, j], 1)


def detect_and_match(cams, maps: dict, min_peak: float = 0.3, epipolar_px: float = 1.0, support_px: float = 1.0,
                     centroid_sigma: float = 1.2, depth_range=(0.5, 3.0)) -> tuple[np.ndarray, dict]:
    """3-D dots (N, 3) from per-view strength maps {camera: (H, W)}, and a summary."""
    names = [c.name for c in cams]
    peaks = [view_peaks(maps[n], min_peak, centroid_sigma).uv for n in names]
    C = len(cams)
    hyps = []
    for a in range(C):
        for b in range(a + 1, C):
            if len(peaks[a]) == 0 or len(peaks[b]) == 0:
                continue
            pairs = _epipolar_pairs(cams[a], cams[b], peaks[a], peaks[b], epipolar_px)
            if len(pairs) == 0:
                continue
            uv = np.full((C, len(pairs), 2), np.nan)
            uv[a] = peaks[a][pairs[:, 0]]
            uv[b] = peaks[b][pairs[:, 1]]
            tr = triangulate(cams, uv)
            X = tr.points
            ok = tr.ok & (tr.max_error < epipolar_px)
            for c, cam in enumerate(cams):        # in front of every camera that took part, at a face's depth
                if c in (a, b):
                    z = cam.project(np.nan_to_num(X))[1]
                    ok &= (z > depth_range[0]) & (z < depth_range[1])
            for k in np.flatnonzero(ok):
                hyps.append((a, int(pairs[k, 0]), b, int(pairs[k, 1]), X[k]))
    if not hyps:
        return np.zeros((0, 3)), {"peaks": [len(p) for p in peaks], "hypotheses": 0, "points": 0}
    from scipy.spatial import cKDTree

    H = len(hyps)
    X0 = np.array([h[4] for h in hyps])
    idx = np.full((C, H), -1)
    for n, (a, i, b, j, _) in enumerate(hyps):
        idx[a, n], idx[b, n] = i, j
    pair = idx >= 0
    # how many candidates every peak has (ambiguity of two-view hypotheses)
    cand = [np.bincount(idx[c][pair[c]], minlength=len(peaks[c])) for c in range(C)]
    for c, cam in enumerate(cams):           # the nearest peak near the projection in every other view
        if len(peaks[c]) == 0:
            continue
        p = cam.project(X0)[0]
        sel = ~pair[c] & np.isfinite(p).all(1)
        if sel.any():
            dist, k = cKDTree(peaks[c]).query(p[sel])
            near = dist < support_px
            idx[c, np.flatnonzero(sel)[near]] = k[near]
    uv = np.full((C, H, 2), np.nan)
    for c in range(C):
        m = idx[c] >= 0
        uv[c, m] = peaks[c][idx[c, m]]
    tr = triangulate(cams, uv, max_error=support_px)
    good = tr.ok & (tr.max_error <= support_px)
    used = tr.used & (idx >= 0)
    nviews = used.sum(0)
    unique = np.ones(H, bool)
    for c in range(C):
        m = used[c]
        unique[m] &= cand[c][idx[c, m]] <= 1
    good &= (nviews >= 3) | unique
    scored = [(-int(nviews[n]), float(tr.error[n]), {c: int(idx[c, n]) for c in range(C) if used[c, n]},
               tr.points[n]) for n in np.flatnonzero(good)]
    scored.sort(key=lambda s: (s[0], s[1]))
    taken = [set() for _ in cams]
    out = []
    for _, _, members, X in scored:
        if any(k in taken[c] for c, k in members.items()):
            continue
        for c, k in members.items():
            taken[c].add(k)
        out.append(X)
    P = np.asarray(out).reshape(-1, 3)
    views = np.bincount([-s[0] for s in scored], minlength=C + 1).tolist() if scored else []
    return P, {"peaks": [len(p) for p in peaks], "hypotheses": len(hyps), "consistent": len(scored),
               "points": len(P), "hypotheses_by_views": views}


def surface_triangles(P: np.ndarray, max_edge_factor: float = 2.5) -> np.ndarray:
    """A triangle mesh over face points (N, 3): Delaunay in (azimuth, height), long edges dropped."""
    from scipy.spatial import Delaunay

    if len(P) < 3:
        return np.zeros((0, 3), np.int64)
    c = P.mean(0)
    az = np.arctan2(P[:, 0] - c[0], P[:, 2] - c[2] + 0.15)
    tri = Delaunay(np.stack([az * 0.15, P[:, 1] - c[1]], 1)).simplices
    L = np.max([np.linalg.norm(P[tri[:, k]] - P[tri[:, (k + 1) % 3]], axis=1) for k in range(3)], axis=0)
    tri = tri[L < max_edge_factor * np.median(L)]
    # counter-clockwise seen from outside (+Z is towards the cameras)
    n = np.cross(P[tri[:, 1]] - P[tri[:, 0]], P[tri[:, 2]] - P[tri[:, 0]])
    out = (P[tri].mean(1) - c)
    flip = np.einsum("ij,ij->i", n, out) < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    return tri.astype(np.int64)


def spread_points(P: np.ndarray, k: int) -> np.ndarray:
    """``k`` indices of P spread out: farthest-point sampling from the point nearest the centre."""
    if len(P) <= k:
        return np.arange(len(P))
    chosen = [int(np.argmin(np.linalg.norm(P - P.mean(0), axis=1)))]
    d = np.linalg.norm(P - P[chosen[0]], axis=1)
    while len(chosen) < k:
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(P - P[i], axis=1))
    return np.array(chosen)


def propose_template(session, n_coarse: int = 18, min_peak: float = 0.3) -> dict:
    """A ``mifacerf.template/1`` dict from the neutral's images, its projections for the page, and notes."""
    from .proposals import untuned_filter
    from ..registration.proxies import proxies_for

    f = untuned_filter(session, use_template=False)
    maps = {c: f.strength(proxies_for(session.cap, session.neutral, c).diffuse, c) for c in session.names}
    P, summary = detect_and_match(session.cams, maps, min_peak=min_peak, centroid_sigma=max(1.2, 1.5 * f.sigma))
    if len(P) < 8:
        return {"template": None, "summary": summary,
                "note": f"only {len(P)} dots matched across views: no template proposed (is the neutral lit, "
                        "are the dots yellow?)"}
    F = surface_triangles(P)
    coarse = spread_points(P, n_coarse)
    doc = {"schema": TEMPLATE_SCHEMA, "units": "metre", "frame": "world",
           "vertices": [{"kind": "dot", "name": f"dot{i}", "position": np.round(p, 7).tolist()}
                        for i, p in enumerate(P)],
           "triangles": F.tolist(), "coarse_points": coarse.tolist(),
           "coarse_triangles": auto_coarse_triangles(P[coarse]).tolist(),
           "dot_radius": DEFAULT_DOT_RADIUS,
           "made_by": "mifacerf studio: proposed from the neutral's images (dots matched across views)"}
    uv = {c.name: np.round(c.project(P)[0], 2).tolist() for c in session.cams}
    fp = centre_footprint(session.cams)
    return {"template": doc, "uv": uv, "summary": summary,
            "note": f"{len(P)} dots found in ≥ 2 views and triangulated ({summary['peaks']} peaks per view), "
                    f"{len(F)} triangles, {len(coarse)} coarse points; margins, eyes, teeth and head points "
                    f"are not proposed (pixel footprint {fp * 1000:.2f} mm)"}
