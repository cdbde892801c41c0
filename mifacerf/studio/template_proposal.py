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
4. **Coarse points**: the two mouth corners (step 5) and ``n_coarse`` − 2 fiducials spread over the face
   (farthest-point sampling from the one nearest the centre, among the dots seen by three or more views
   and by two at cos ≥ 0.5), with their Delaunay mesh.

5. **Mouth and eyes** from the proxy images (:mod:`.features`): the lip margins from the mouth line (the
   darkest row of the red lip blob, lifted to 3-D by the other views' mouth lines with the dots' surface as
   the prior; the upper and lower margins 0.7 mm either side of it, sharing the corners), the eyelid
   margins from the edges of the eye opening (the white of the eye closed over the iris; lifted with the
   eyeball as the prior), the **eyes** from the iris discs (their centres triangulated; the eyeball centre
   ``iris_depth`` behind along the face's forward axis, radius 12 mm, the iris radius from the disc's
   width). The surface triangulation then includes the margin vertices and leaves the mouth and the eyes
   open (holes).
6. **Teeth**: two strips of ten teeth on an arc behind the lips (front 11 mm behind the mouth line, as wide
   as 0.9 of the mouth, 23 mm deep at the sides), the upper above the mouth line, the lower below, its mark
   the front centre of its top edge.
7. **Regions** (forehead, nose, eyes, mouth, chin, cheeks, throat, neck) from the geometry: each vertex's
   position in the face's frame (origin between the eyes, x towards the subject's left eye, y up) against
   the eyes and the mouth line. **Head points**: the dots farthest out on either side at eye height
   (``ear_L``, ``ear_R``, rigid with the skull) and the dot nearest the bridge of the nose.

Not proposed: the nostril vertices (the nose is carried by its dots). What cannot be found (no lip blob,
fewer than two views of an eye) is left out and said in the note; registration flags what is missing.
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
                     centroid_sigma: float = 1.2, depth_range=(0.5, 3.0), grow: bool | dict = True,
                     min_spacing_px: float = 7.0) -> tuple[np.ndarray, dict]:
    """3-D dots (N, 3) from per-view strength maps {camera: (H, W)}, and a summary. ``grow``: add the
    ambiguous two-view hypotheses that continue the surface of the others (:func:`_grow_on_surface`;
    a dict: its parameters) where the dots found are at least ``min_spacing_px`` apart in the images
    (median nearest neighbour over the centre pixel footprint). Measured: on ``draft`` (9.8 px) growing
    adds 39 points, one matching no true fiducial; on ``tiny`` (5.4 px) 57, 29 matching none (some 6-10
    cm off): the threshold lies between the two."""
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
    ambiguous = good & ~((nviews >= 3) | unique)
    good &= (nviews >= 3) | unique
    scored = [(-int(nviews[n]), float(tr.error[n]), {c: int(idx[c, n]) for c in range(C) if used[c, n]},
               tr.points[n]) for n in np.flatnonzero(good)]
    scored.sort(key=lambda s: (s[0], s[1]))
    taken = [set() for _ in cams]
    out, nv = [], []
    for nviews_neg, _, members, X in scored:
        if any(k in taken[c] for c, k in members.items()):
            continue
        for c, k in members.items():
            taken[c].add(k)
        out.append(X)
        nv.append(-nviews_neg)
    n_strong = len(out)
    spacing_px = 0.0
    if len(out) >= 8:
        from scipy.spatial import cKDTree as _Tree

        spacing_px = float(np.median(_Tree(np.asarray(out)).query(np.asarray(out), k=2)[0][:, 1])) \
            / centre_footprint(cams)
    # dots fewer than ``min_spacing_px`` apart in the images: a wrong pairing lies too near the surface
    if grow and len(out) >= 8 and spacing_px >= min_spacing_px:
        rest = [({c: int(idx[c, n]) for c in range(C) if used[c, n]}, tr.points[n]) for n in np.flatnonzero(ambiguous)]
        for X in _grow_on_surface(out, rest, taken, **(grow if isinstance(grow, dict) else {})):
            out.append(X)
            nv.append(2)
    P = np.asarray(out).reshape(-1, 3)
    views = np.bincount([-s[0] for s in scored], minlength=C + 1).tolist() if scored else []
    return P, {"peaks": [len(p) for p in peaks], "hypotheses": len(hyps), "consistent": len(scored),
               "points": len(P), "grown": len(P) - n_strong, "spacing_px": round(spacing_px, 2),
               "hypotheses_by_views": views, "views_per_point": nv}


def _grow_on_surface(accepted: list, rest: list, taken: list, neighbours: int = 6, radius: float = 0.05,
                     min_sep: float = 0.004, tol: float = 0.004, margin: float = 2.0) -> list:
    """Ambiguous two-view hypotheses ``rest`` [(members {view: peak}, X)] taken where they continue the
    surface of the ``accepted`` points: best first by the distance from the plane through the ``neighbours``
    accepted points nearest (within ``radius``; at least 4), at most ``tol``, no accepted point within
    ``min_sep``, and every rival sharing one of its peaks ``margin`` times farther off (a wrong pairing of
    two views' dots lies centimetres in front of or behind the face). Rounds until none is added; marks
    the peaks in ``taken``. Returns the points added."""
    from scipy.spatial import cKDTree

    added = []
    rest = list(rest)
    while rest:
        A = np.asarray(accepted + added)
        tree = cKDTree(A)
        dist, nb = tree.query(np.array([X for _, X in rest]), k=min(neighbours, len(A)),
                              distance_upper_bound=radius)
        dist, nb = dist.reshape(len(rest), -1), nb.reshape(len(rest), -1)
        score = np.full(len(rest), np.inf)
        for r, (members, X) in enumerate(rest):
            if any(k in taken[c] for c, k in members.items()) or dist[r, 0] < min_sep:
                continue
            ok = np.isfinite(dist[r])
            if ok.sum() < 4:
                continue
            Q = A[nb[r, ok]]
            c0 = Q.mean(0)
            normal = np.linalg.svd(Q - c0)[2][-1]
            score[r] = abs(float((X - c0) @ normal))
        keep = []
        for r in np.argsort(score):
            if not score[r] <= tol:
                break
            members = rest[r][0]
            if any(k in taken[c] for c, k in members.items()):
                continue
            rivals = [q for q in range(len(rest)) if q != r
                      and any(rest[q][0].get(c) == k for c, k in members.items())]
            if any(score[q] < margin * score[r] + 5e-4 for q in rivals):
                continue
            for c, k in members.items():
                taken[c].add(k)
            keep.append(r)
        if not keep:
            break
        added += [rest[r][1] for r in keep]
        rest = [h for q, h in enumerate(rest) if q not in set(keep)]
    return added


def _flat(P: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N, 2) the points' (azimuth about the vertical axis, height) as seen from in front, in metres."""
    az = np.arctan2(P[:, 0] - c[0], P[:, 2] - c[2] + 0.15)
    return np.stack([az * 0.15, P[:, 1] - c[1]], 1)


def surface_triangles(P: np.ndarray, max_edge_factor: float = 2.5, max_edge: float | None = None,
                      centre: np.ndarray | None = None) -> np.ndarray:
    """A triangle mesh over face points (N, 3): Delaunay in (azimuth, height), edges longer than
    ``max_edge`` (default ``max_edge_factor`` × the median longest edge) dropped."""
    from scipy.spatial import Delaunay

    if len(P) < 3:
        return np.zeros((0, 3), np.int64)
    c = P.mean(0) if centre is None else centre
    tri = Delaunay(_flat(P, c)).simplices
    L = np.max([np.linalg.norm(P[tri[:, k]] - P[tri[:, (k + 1) % 3]], axis=1) for k in range(3)], axis=0)
    tri = tri[L < (max_edge if max_edge is not None else max_edge_factor * np.median(L))]
    # counter-clockwise seen from outside: away from the head's vertical axis (behind the points' centre;
    # +Z is towards the cameras) — not away from the centre itself, which would turn the neck's triangles in
    n = np.cross(P[tri[:, 1]] - P[tri[:, 0]], P[tri[:, 2]] - P[tri[:, 0]])
    out = P[tri].mean(1) - np.array([c[0], 0.0, c[2] - 0.05])
    out[:, 1] = 0.0
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


def _face_frame(eyes: dict, P: np.ndarray):
    """(origin, x, y, z): between the eyes, x towards the subject's left eye, y up, z forward."""
    if "L" in eyes and "R" in eyes:
        o = 0.5 * (eyes["L"]["iris"] + eyes["R"]["iris"])
        x = eyes["L"]["iris"] - eyes["R"]["iris"]
        x = x / np.linalg.norm(x)
    else:
        o = P.mean(0) + np.array([0.0, 0.04, 0.0]) if "L" not in eyes and "R" not in eyes else \
            next(iter(eyes.values()))["iris"]
        x = np.array([1.0, 0.0, 0.0])
    y = np.array([0.0, 1.0, 0.0]) - x[1] * x
    y /= np.linalg.norm(y)
    return o, x, y, np.cross(x, y)


def teeth_strips(line: np.ndarray, frame, n_teeth: int = 10) -> dict:
    """Upper and lower teeth strips (``mifacerf.template/1`` ``teeth``) behind the mouth line (n, 3)."""
    o, ex, ey, ez = frame
    mid = line[len(line) // 2]
    half = 0.45 * float(np.linalg.norm(line[-1] - line[0]))
    front = mid - 0.011 * ez
    xs = np.linspace(-half, half, n_teeth + 1)
    arc = front + xs[:, None] * ex - (0.023 * (xs / max(half, 1e-6)) ** 2)[:, None] * ez
    out = {}
    for part, (a, b) in (("upper", (-0.001, 0.0078)), ("lower", (0.0005, -0.0085))):
        V = np.stack([arc + a * ey, arc + b * ey], 1).reshape(-1, 3)      # 2 per column: edge, root
        F = []
        for k in range(n_teeth):
            i = 2 * k
            F += [[i, i + 2, i + 3], [i, i + 3, i + 1]]
        F = np.array(F)
        n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        centre = front - 0.03 * ez
        flip = np.einsum("ij,ij->i", n, V[F].mean(1) - centre) < 0
        F[flip] = F[flip][:, [0, 2, 1]]
        out[part] = {"part": f"teeth_{part}", "vertices": np.round(V, 7).tolist(), "triangles": F.tolist()}
    out["lower"]["mark"] = 2 * (n_teeth // 2)          # the front centre of the lower strip's top edge
    return out


def assign_regions(V: np.ndarray, kinds: list, frame, mouth_y: float | None, eyes: dict) -> dict:
    """The culling regions (docs/registration.md) from the neutral positions in the face's frame."""
    o, ex, ey, ez = frame
    q = np.stack([(V - o) @ ex, (V - o) @ ey, (V - o) @ ez], 1)
    ym = mouth_y if mouth_y is not None else -0.072
    axis = np.median(q[[k == "dot" for k in kinds], 2]) - 0.02
    eye_q = {s: np.array([(e["centre"] - o) @ ex, (e["centre"] - o) @ ey, (e["centre"] - o) @ ez])
             for s, e in eyes.items()}
    names = ("forehead", "mouth", "neck", "throat", "chin", "cheek_left", "cheek_right", "eye_left", "eye_right",
             "nose")
    out = {k: [] for k in names}
    for i, (x, y, z) in enumerate(q):
        k = kinds[i]
        side = "left" if x > 0 else "right"
        e = eye_q.get("L" if x > 0 else "R")
        if k.startswith("lip"):
            r = "mouth"
        elif k.startswith("lid"):
            r = f"eye_{side}"
        elif y < ym - 0.038 or (y < ym - 0.018 and z < -0.025):
            r = "throat" if abs(np.arctan2(x, z - axis)) < np.radians(38) else "neck"
        elif y > 0.029:
            r = "forehead"
        elif abs(x) < 0.016 and ym + 0.017 < y < 0.007 and z > 0.004:
            r = "nose"
        elif e is not None and np.linalg.norm(q[i] - e) < 0.030 and y > -0.015:
            r = f"eye_{side}"
        elif abs(x) < 0.036 and ym - 0.013 < y < ym + 0.023 and z > -0.016:
            r = "mouth"
        elif abs(x) < 0.036 and y <= ym - 0.013 and z > -0.026:
            r = "chin"
        else:
            r = f"cheek_{side}"
        out[r].append(i)
    return {k: v for k, v in out.items() if v}


def _point_in_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    inside = np.zeros(len(pts), bool)
    x, y = pts[:, 0], pts[:, 1]
    for (x0, y0), (x1, y1) in zip(poly, np.roll(poly, -1, axis=0)):
        cross = (y0 > y) != (y1 > y)
        xi = x0 + (y - y0) * (x1 - x0) / np.where(y1 != y0, y1 - y0, 1e-12)
        inside ^= cross & (x < xi)
    return inside


def head_point_dots(P: np.ndarray, frame) -> dict:
    """Dots standing in for the head points: the farthest out on either side at eye height (ear_L,
    ear_R) and the one nearest the bridge of the nose."""
    o, ex, ey, ez = frame
    q = np.stack([(P - o) @ ex, (P - o) @ ey, (P - o) @ ez], 1)
    band = np.abs(q[:, 1]) < 0.025
    out = {}
    if band.sum() >= 2:
        ids = np.flatnonzero(band)
        out["ear_L"] = int(ids[np.argmax(q[ids, 0])])
        out["ear_R"] = int(ids[np.argmin(q[ids, 0])])
    d = np.linalg.norm(q[:, :2] - [0.0, 0.0], axis=1) - 0.3 * q[:, 2]
    out["nose_bridge"] = int(np.argmin(d))
    if len(set(out.values())) < len(out):
        return {}
    return out


def propose_template(session, n_coarse: int = 18, min_peak: float = 0.3) -> dict:
    """A ``mifacerf.template/1`` dict from the neutral's images, its projections for the page, and notes."""
    from .features import find_face
    from .proposals import untuned_filter
    from ..registration.proxies import proxies_for

    f = untuned_filter(session, use_template=False)
    images = {c: proxies_for(session.cap, session.neutral, c).diffuse for c in session.names}
    maps = {c: f.strength(images[c], c) for c in session.names}
    P, summary = detect_and_match(session.cams, maps, min_peak=min_peak, centroid_sigma=max(1.2, 1.5 * f.sigma))
    if len(P) < 8:
        return {"template": None, "summary": summary,
                "note": f"only {len(P)} dots matched across views: no template proposed (is the neutral lit, "
                        "are the dots yellow?)"}
    face = find_face(session.cams, images, P, triangles=surface_triangles(P))
    notes = list(face["notes"])
    frame = _face_frame(face["eyes"], P)
    verts = [{"kind": "dot", "name": f"dot{i}", "position": p} for i, p in enumerate(P)]

    def add(kind, name, p):
        verts.append({"kind": kind, "name": name, "position": np.asarray(p, np.float64)})
        return len(verts) - 1
    margins, holes = {}, {}
    mouth_y = None
    if face["mouth"] is not None:
        line = face["mouth"]["line"]
        mouth_y = float((line[len(line) // 2] - frame[0]) @ frame[2])     # height below the eyes
        a, b = add("lip_corner", "mouth_corner_R", line[0]), add("lip_corner", "mouth_corner_L", line[-1])
        up = [add("lip_upper", f"lip_upper{k}", p + 7e-4 * frame[2]) for k, p in enumerate(line[1:-1])]
        lo = [add("lip_lower", f"lip_lower{k}", p - 7e-4 * frame[2]) for k, p in enumerate(line[1:-1])]
        margins["lip_upper"], margins["lip_lower"] = [a] + up + [b], [a] + lo + [b]
        holes["mouth"] = [a] + up + [b] + lo[::-1]
    for side, hole in (("L", "eye_left"), ("R", "eye_right")):
        e = face["eyes"].get(side)
        if e is None:
            continue
        a, b = add("lid_corner", f"lid_corner_{side}0", e["upper"][0]), add("lid_corner", f"lid_corner_{side}1",
                                                                            e["upper"][-1])
        up = [add("lid_upper", f"lid_upper_{side}{k}", p) for k, p in enumerate(e["upper"][1:-1])]
        lo = [add("lid_lower", f"lid_lower_{side}{k}", p) for k, p in enumerate(e["lower"][1:-1])]
        margins[f"lid_upper_{side}"], margins[f"lid_lower_{side}"] = [a] + up + [b], [a] + lo + [b]
        holes[hole] = [a] + up + [b] + lo[::-1]
    V = np.array([v["position"] for v in verts])
    kinds = [v["kind"] for v in verts]
    # the surface over every vertex, the long edges of the dots' own mesh dropped, the openings left open
    F0 = surface_triangles(P)
    L0 = np.max([np.linalg.norm(P[F0[:, k]] - P[F0[:, (k + 1) % 3]], axis=1) for k in range(3)], axis=0)
    c = P.mean(0)
    F = surface_triangles(V, max_edge=float(L0.max()) + 1e-9, centre=c)
    flat = _flat(V, c)
    drop = np.zeros(len(F), bool)
    for loop in holes.values():
        loop = np.asarray(loop)
        drop |= _point_in_polygon(flat[F].mean(1), flat[loop])
        n = len(loop)
        half = (n + 2) // 2       # [corner, upper..., corner, lower reversed...]
        upper, lower = set(loop[1:half - 1].tolist()), set(loop[half:].tolist())
        for t, tri in enumerate(F):
            if upper & set(tri.tolist()) and lower & set(tri.tolist()):
                drop[t] = True
    F = F[~drop]
    # coarse points among the dots seen by the most views (every expression must show them), spread out
    nv = np.asarray(summary.pop("views_per_point"))
    from ..geometry.visibility import Visibility

    seen = Visibility(F, len(V), tol=max(0.5 * centre_footprint(session.cams), 5e-4))(
        V, session.cams, min_cos=0.5).sum(0)[:len(P)]
    pool = np.flatnonzero((nv >= min(3, nv.max())) & (seen >= 2))
    if len(pool) < n_coarse:
        pool = np.arange(len(P))
    corners = [margins["lip_upper"][0], margins["lip_upper"][-1]] if "lip_upper" in margins else []
    coarse = np.concatenate([pool[spread_points(P[pool], n_coarse - len(corners))],
                             np.asarray(corners, np.int64)]).astype(np.int64)
    head = head_point_dots(P, frame)
    eyes = {("eye_left" if s == "L" else "eye_right"): {
        "centre": np.round(e["centre"], 7).tolist(), "radius": e["radius"], "iris_radius": round(e["iris_radius"], 7),
        "iris_depth": round(e["iris_depth"], 7)} for s, e in face["eyes"].items()}
    teeth = teeth_strips(face["mouth"]["line"], frame) if face["mouth"] is not None else {}
    regions = assign_regions(V, kinds, frame, mouth_y, face["eyes"])
    doc = {"schema": TEMPLATE_SCHEMA, "units": "metre", "frame": "world",
           "vertices": [{"kind": v["kind"], "name": v["name"], "position": np.round(v["position"], 7).tolist()}
                        for v in verts],
           "triangles": F.tolist(), "coarse_points": coarse.tolist(),
           "coarse_triangles": auto_coarse_triangles(V[coarse]).tolist(),
           "margins": {k: [int(i) for i in v] for k, v in margins.items()},
           "holes": {k: [int(i) for i in v] for k, v in holes.items()},
           "regions": {k: [int(i) for i in v] for k, v in regions.items()},
           "eyes": eyes, "teeth": teeth, "head_points": head,
           "dot_radius": DEFAULT_DOT_RADIUS,
           "made_by": "mifacerf studio: proposed from the neutral's images (dots matched across views, "
                      "lips and eyes from the proxy images)"}
    uv = {c.name: np.round(np.nan_to_num(c.project(V)[0], nan=-1e4), 2).tolist() for c in session.cams}
    fp = centre_footprint(session.cams)
    summary.update({"margins": {k: len(v) for k, v in margins.items()}, "eyes": sorted(face["eyes"]),
                    "mouth_views": face["mouth"]["views"] if face["mouth"] else [],
                    "regions": {k: len(v) for k, v in regions.items()}, "head_points": head})
    return {"template": doc, "uv": uv, "summary": summary, "kinds": kinds,
            "note": f"{len(P)} dots found in ≥ 2 views and triangulated ({summary['peaks']} peaks per view), "
                    f"{len(F)} triangles, {len(coarse)} coarse points; {len(margins)} lip / eyelid margins, "
                    f"{len(eyes)} eyes, {'teeth' if teeth else 'no teeth'}, {len(regions)} regions"
                    + (f"; {'; '.join(notes)}" if notes else "") + f" (pixel footprint {fp * 1000:.2f} mm)"}
