"""Hand inputs proposed by the studio, so the user verifies rather than clicks (beyond the paper).

* :func:`untuned_filter` — a dot filter before any registration (tuned on the template's fiducials if
  there is a template, else the prior yellow colour direction of :mod:`mifacerf.registration.dots`).
* :func:`propose_expression` — for an expression, from the nearest registered expression ``R`` (the
  one whose registered fiducials, projected into this expression's views, land on the most dot
  strength; the template itself before anything is registered): ``R``'s template is carried onto this
  expression by its dots (:func:`follow_dots`: a rigid alignment that lands ``R``'s fiducials on the most
  dot strength, then rounds of snapping every fiducial to its nearest dot and moving every vertex by the
  median displacement of its nearest snapped fiducials); the coarse points are that template's coarse
  vertices snapped to this expression's dots and triangulated; the lip and eyelid margins, the head
  points and the lower-teeth mark are projected from it into the views ``R``'s rotoscoping used (or the
  two views facing the face most directly); the irises are ``R``'s curves moved with the eyelids (or the
  template's limbus looking forward).
  Coarse points that are mouth corners are clicked where the lips' colour ends in the two views facing
  the mouth (:func:`_mouth_corners_from_images`), and doubtful coarse proposals are flagged
  (:func:`flag_coarse`).
* :func:`propose_template` — a template from the neutral's images alone (:mod:`.template_proposal`).

Proposals are never written by themselves: the page shows them and the user accepts, moves or deletes
each one. Nothing here reads ``truth/``.
"""
from __future__ import annotations

import numpy as np

from ..geometry.footprint import centre_footprint
from ..registration.dots import DotFilter, PRIOR_YELLOW, face_mask, peak_near
from ..registration.hand import DEFAULT_DOT_RADIUS


def untuned_filter(session, use_template: bool = True) -> DotFilter:
    """A dot filter without a registration (see the module docstring)."""
    from ..registration.proxies import proxies_for

    tpl = session.template() if use_template else None
    radius_px = (tpl.dot_radius if tpl is not None else DEFAULT_DOT_RADIUS) / centre_footprint(session.cams)
    diffuse = {c: proxies_for(session.cap, session.neutral, c).diffuse for c in session.names}
    if tpl is not None and len(tpl.dot_ids):
        V = tpl.vertices[tpl.dot_ids]
        uvs = {c.name: c.project(V)[0] for c in session.cams}
        try:
            return DotFilter.fit(diffuse, uvs, radius_px)
        except ValueError:
            pass
    sigma, surround, norm_sigma = DotFilter.sizes(radius_px)
    probe = DotFilter(PRIOR_YELLOW.copy(), sigma, surround, norm_sigma)
    img = next(iter(diffuse.values()))
    mask = face_mask(img)
    colour = PRIOR_YELLOW.copy()
    if mask.sum() >= 10:
        skin = np.median(probe.normalised(img)[mask], axis=0)
        s = skin / np.linalg.norm(skin)
        colour = PRIOR_YELLOW - (PRIOR_YELLOW @ s) * s
        colour /= np.linalg.norm(colour)
    f = DotFilter(colour, sigma, surround, norm_sigma)
    from scipy.ndimage import maximum_filter

    for cam, d in diffuse.items():
        r = np.maximum(f.response(d), 0)
        pk = r[(r >= maximum_filter(r, size=3)) & face_mask(d)]
        pk = np.sort(pk[pk > 0])[::-1]
        if len(pk):
            f.scales[cam] = float(np.median(pk[: max(5, len(pk) // 3)]))   # the stronger third: dots, not skin
    return f


def _strength_maps(session, name: str) -> dict:
    return {c: session.float_image(name, c, "dots") for c in session.names}


def nearest_registered(session, name: str, maps: dict | None = None) -> str | None:
    """The registered expression whose registered fiducials, projected here, meet the most dot strength."""
    tpl = session.template()
    if tpl is None:
        return None
    maps = maps or _strength_maps(session, name)
    best, best_s = None, -1.0
    for e in session.cap.expression_names:
        if e == name:
            continue
        reg = session.registered(e)
        if reg is None or len(reg.vertices) != tpl.n_vertices:
            continue
        ids = tpl.dot_ids[reg.status[tpl.dot_ids] == 1]
        s = 0.0
        for c, cam in enumerate(session.cams):
            sel = ids[reg.visible[c, ids]]
            if len(sel):
                uv = cam.project(reg.vertices[sel])[0]
                s += float(peak_near(maps[cam.name], uv, 1.0)[1].sum())
        if s > best_s:
            best, best_s = e, s
    return best


def _best_views(session, X: np.ndarray, normal_hint: np.ndarray, k: int = 2) -> list:
    """The ``k`` cameras looking most directly at points X (n, 3) along ``normal_hint`` (3,)."""
    c0 = X.mean(0)
    cos = []
    for cam in session.cams:
        d = cam.centre - c0
        cos.append(float(d @ normal_hint / (np.linalg.norm(d) * max(np.linalg.norm(normal_hint), 1e-12))))
    order = np.argsort(cos)[::-1]
    return [session.names[i] for i in order[:k] if cos[i] > 0.1]


def propose_expression(session, name: str) -> dict:
    """Proposed hand state (the session's format, :mod:`.session`) for ``name``, with ``source`` and notes."""
    from ..geometry.triangulate import triangulate

    session.check_expression(name)
    tpl = session.template()
    if tpl is None:
        return {"source": None, "note": "no template yet: propose one on the neutral first", "state": None}
    maps = _strength_maps(session, name)
    src = nearest_registered(session, name, maps)
    if src is not None:
        R = session.registered(src)
    elif session.registered(session.neutral) is None:
        src, R = "template", _template_as_registered(session, tpl)     # nothing registered yet: the template
    else:
        return {"source": None, "note": "no registered expression to propose from", "state": None}
    fp = centre_footprint(session.cams)
    search = max(1.5, 0.35 * _dot_spacing(tpl) / fp)
    coarse = tpl.coarse
    V, track = follow_dots(session, tpl, R, maps, search)
    # the coarse points: the followed template's coarse vertices snapped to this expression's dots
    uvV = np.stack([cam.project(V[coarse])[0] for cam in session.cams])               # (C, K, 2)
    vis = track["visible"][:, coarse]
    clicks = np.full_like(uvV, np.nan)
    for c, cam in enumerate(session.cams):
        pk, val = peak_near(maps[cam.name], uvV[c], min(search, 1.0))
        good = vis[c] & (val >= 0.25) & np.isfinite(pk).all(1)
        # a non-dot coarse point (mouth corner, ear) has no dot: the followed template's projection
        nodot = vis[c] & ~tpl.is_dot[coarse]
        clicks[c, good] = pk[good]
        clicks[c, nodot] = uvV[c, nodot]
    moved = {} if src == "template" else _mouth_corners_from_images(session, name, tpl, coarse, clicks, vis, fp)
    tr = triangulate(session.cams, clicks, max_error=1.0)
    ok = tr.ok & (tr.max_error <= 1.0)
    state = {"coarse": {}, "rotoscope": {"curves": {}, "points": {}, "eyes_look_at": None}, "overrides": {}}
    # a coarse fiducial the followed template did not itself put on a dot sits where its neighbours put
    # it: its nearest dot may be another one, and registration pins coarse points — left to the user
    # (registration carries a missing coarse point from its clicked neighbours)
    followed = np.zeros(tpl.n_vertices, bool)
    followed[track["snapped"]] = True
    unsure = tpl.is_dot[coarse] & ~followed[coarse]
    if src == "template":
        unsure[:] = False           # the neutral: the template's own positions
    ok &= ~unsure
    for j, vid in enumerate(coarse):
        if ok[j]:
            state["coarse"][str(int(vid))] = {
                "clicks": {n: np.round(clicks[c, j], 3).tolist() for c, n in enumerate(session.names)
                           if tr.used[c, j]},
                "position": np.round(tr.points[j], 7).tolist()}
    rot_src = session.hand_state(src)["rotoscope"] if src != "template" else {"curves": {}, "points": {}}
    forward = np.array([0.0, 0.0, 1.0])
    for mname, ids in tpl.margins.items():
        views = [c for c in rot_src["curves"].get(mname, {}) if c in session.names] or \
            _best_views(session, V[ids], forward)
        if len(views) >= 2:
            state["rotoscope"]["curves"][mname] = {
                c: np.round(session.camera(c).project(_dense(V[ids]))[0], 3).tolist() for c in views}
    for side in ("L", "R"):
        curve = rot_src["curves"].get(f"iris_{side}")
        if not curve:
            circle = _iris_from_template(tpl, side, R, V)
            if circle is not None:
                views = _best_views(session, circle, forward)
                if len(views) >= 2:
                    state["rotoscope"]["curves"][f"iris_{side}"] = {
                        c: np.round(session.camera(c).project(circle)[0], 3).tolist() for c in views}
            continue
        out = {}
        for c, poly in curve.items():
            if c not in session.names:
                continue
            cam = session.camera(c)
            ids = tpl.margins.get(f"lid_upper_{side}", np.zeros(0, np.int64))
            shift = 0.0
            if len(ids):
                shift = np.nanmean(cam.project(V[ids])[0] - cam.project(R.vertices[ids])[0], axis=0)
            out[c] = np.round(np.asarray(poly, np.float64) + shift, 3).tolist()
        if len(out) >= 2:
            state["rotoscope"]["curves"][f"iris_{side}"] = out
    for pname, vid in tpl.head_points.items():
        if int(vid) in set(coarse.tolist()):
            continue
        views = [c for c in rot_src["points"].get(pname, {}) if c in session.names] or \
            _best_views(session, V[[vid]], V[vid] - V.mean(0), 2)
        if len(views) >= 2:
            state["rotoscope"]["points"][pname] = {c: np.round(session.camera(c).project(V[[vid]])[0][0], 3).tolist()
                                                   for c in views}
    lt = tpl.lower_teeth_point
    if lt is not None and np.isfinite(R.teeth[1]).all():
        pR = R.teeth[1][:3, :3] @ lt + R.teeth[1][:3, 3]
        chin = np.asarray(tpl.regions.get("chin", []), np.int64)
        if len(chin) >= 3:        # carried by the jaw: the morph's rigid motion of the chin
            from ..geometry.rigid import apply, rigid_from_points

            p = apply(rigid_from_points(R.vertices[chin], V[chin]), pR[None])[0]
        else:                     # ... or the morph's displacement of the nearest template vertex
            k = int(np.argmin(np.linalg.norm(R.vertices - pR, axis=1)))
            p = pR + (V[k] - R.vertices[k])
        views = [c for c in rot_src["points"].get("lower_teeth", {}) if c in session.names]
        up, lo = tpl.margins.get("lip_upper"), tpl.margins.get("lip_lower")
        if not views and up is not None and lo is not None and len(up) > 2 and len(lo) > 2:
            gap = np.linalg.norm(V[up[len(up) // 2]] - V[lo[len(lo) // 2]])
            if gap > 0.004:       # the mouth is open: the teeth show in the views facing the face
                views = _best_views(session, p[None], forward)
        if len(views) >= 2:
            state["rotoscope"]["points"]["lower_teeth"] = {
                c: np.round(session.camera(c).project(p[None])[0][0], 3).tolist() for c in views}
    state["rotoscope"]["eyes_look_at"] = rot_src.get("eyes_look_at")
    flagged = flag_coarse(session, tpl, R, state["coarse"], tr.max_error, coarse, fp)
    for v, why in flag_jaw(session, tpl, R, src, name, V, coarse, fp).items():
        if v in state["coarse"]:
            c = flagged["coarse"]
            c[v] = (c[v] + "; " if v in c else "") + why
    for v, d in moved.items():
        flagged.setdefault("moved", {})[str(v)] = f"moved {d:.1f} px to the lips' end in the images"
    n_ok = int(ok.sum())
    return {"source": src, "state": state, "unsure_coarse": coarse[unsure].tolist(), "flagged": flagged,
            "note": f"from {src}: {n_ok} of {len(coarse)} coarse points found on this expression's dots"
                    + (f" ({int(unsure.sum())} left for you: {coarse[unsure].tolist()}, not found on a dot)"
                       if unsure.any() else "") + "; "
                    f"{len(state['rotoscope']['curves'])} curves and {len(state['rotoscope']['points'])} marks "
                    "projected from the template carried by the dots"
                    + (f"; check the flagged ones: " + "; ".join(f"{v}: {why}" for v, why in flagged["coarse"].items())
                       if flagged["coarse"] else "")}


def _mouth_corners_from_images(session, name: str, tpl, coarse: np.ndarray, clicks: np.ndarray, vis: np.ndarray,
                               fp: float, reach_px: float = 15.0) -> dict:
    """Coarse points that are mouth corners (kind ``lip_corner``) clicked where the lips end in each view
    (:func:`.features.mouth_corners`; the end nearest the followed template's corner, within ``reach_px``)
    in the two views facing the mouth most directly (seen from the side, the lips end at their silhouette,
    not at the corner), instead of at the followed template's projection: an open jaw drags the
    template's corners onto the wrong dots, the lips' colour does not move with them. ``clicks`` (C, K, 2)
    is changed in place (the other views' clicks of those points dropped); returns {vertex id: how far
    (px, the views' median) the clicks moved}."""
    from .features import lips_region, mouth_corners
    from ..registration.dots import face_mask

    js = [j for j, v in enumerate(coarse) if tpl.kinds[int(v)] == "lip_corner"]
    if not js:
        return {}
    ends = {}
    X = tpl.vertices[coarse[js]].mean(0)
    facing = set(_best_views(session, X[None], np.array([0.0, 0.0, 1.0]), 2))
    for c, cam in enumerate(session.cams):
        if cam.name not in facing:
            continue
        img = session.float_image(name, cam.name, "diffuse")
        region = lips_region(img, face_mask(img))
        if region is not None:
            ends[c] = mouth_corners(region)
    moved = {}
    for j in js:
        shifts = []
        for c, e in ends.items():
            if not vis[c, j] or not np.isfinite(clicks[c, j]).all():
                continue
            d = np.linalg.norm(e - clicks[c, j], axis=1)
            k = int(np.argmin(d))
            if d[k] <= reach_px:
                shifts.append(float(d[k]))
                clicks[c, j] = e[k]
        if len(shifts) == 2:
            for c in range(len(session.cams)):
                if c not in ends:
                    clicks[c, j] = np.nan
            if np.median(shifts) > 1.0:
                moved[int(coarse[j])] = float(np.median(shifts))
    return moved


#: a proposed coarse point is flagged when its views disagree by more than this (px) ...
FLAG_REPROJ_PX = 0.6
#: ... or when it is farther than this (pixel footprints) from where the other coarse points' motion
#: from the reference (moving-least-squares affine, leave-one-out) puts it
FLAG_MORPH_PX = 8.0


def flag_coarse(session, tpl, R, coarse_state: dict, max_error: np.ndarray, coarse: np.ndarray, fp: float) -> dict:
    """{"coarse": {vertex id: reason}}: proposed coarse points that look wrong — views that disagree
    (reprojection residual above :data:`FLAG_REPROJ_PX`), or a motion from the reference ``R`` that its
    neighbours do not share (leave-one-out MLS-affine prediction from the other proposed coarse points
    farther than :data:`FLAG_MORPH_PX` footprints; a point landed on a neighbouring dot shows as one dot
    spacing off). The page draws them in the flagged colour and the note lists them."""
    from ..geometry.schaefer2006 import mls_affine

    out = {}
    ids = [int(v) for v in coarse_state]
    j_of = {int(v): j for j, v in enumerate(coarse)}
    for v in ids:
        e = float(max_error[j_of[v]])
        if np.isfinite(e) and e > FLAG_REPROJ_PX:
            out[str(v)] = f"its views disagree by {e:.2f} px"
    if len(ids) >= 6:
        src = R.vertices[ids]
        dst = np.array([coarse_state[str(v)]["position"] for v in ids])
        for k, v in enumerate(ids):
            others = [i for i in range(len(ids)) if i != k]
            pred = mls_affine(src[others], dst[others], src[k:k + 1], k=6)[0]
            off = float(np.linalg.norm(pred - dst[k])) / fp
            if off > FLAG_MORPH_PX:
                out[str(v)] = (out.get(str(v), "") + "; " if str(v) in out else "") + \
                    f"{off:.1f} px from where the other coarse points' motion puts it"
    return {"coarse": out}


def _lip_bottom_offset(region: np.ndarray, uv: np.ndarray) -> float | None:
    """Median over the points ``uv`` (n, 2) of (lowest lip pixel in the point's column − the point's row);
    None where no column holds lip."""
    offs = []
    for u, v in uv:
        col = int(round(u))
        if np.isfinite(u) and 0 <= col < region.shape[1]:
            rows = np.flatnonzero(region[:, col])
            if len(rows):
                offs.append(rows.max() - v)
    return float(np.median(offs)) if len(offs) >= 3 else None


def flag_jaw(session, tpl, R, src: str, name: str, V: np.ndarray, coarse: np.ndarray, fp: float) -> dict:
    """{vertex id: reason} for the coarse points below the mouth line when the followed template's lower lip
    has moved differently from the lips' colour: in the two views facing the mouth, the lowest lip pixel
    below the lower-lip margin's vertices, against the same in the reference ``R`` (its own images), shifted
    by more than half a dot spacing — an open jaw that landed on the neighbouring dots moves its lip margin
    with it, the lips' colour does not. Nothing when ``R`` is the template."""
    from ..registration.dots import face_mask
    from .features import lips_region

    lo = np.asarray(tpl.margins.get("lip_lower", []), np.int64)
    if src == "template" or len(lo) < 5 or src not in session.cap.expression_names:
        return {}
    lo = lo[1:-1]                              # not the corners
    views = _best_views(session, V[lo], np.array([0.0, 0.0, 1.0]), 2)
    shifts = []
    for cn in views:
        cam = session.camera(cn)
        got = []
        for expr, P in ((src, R.vertices), (name, V)):
            img = session.float_image(expr, cn, "diffuse")
            region = lips_region(img, face_mask(img))
            got.append(None if region is None else _lip_bottom_offset(region, cam.project(P[lo])[0]))
        if None not in got:
            shifts.append(got[1] - got[0])
    if not shifts:
        return {}
    shift = float(np.median(shifts))
    if abs(shift) <= 0.5 * _dot_spacing(tpl) / fp:
        return {}
    lips = np.concatenate([np.asarray(tpl.margins.get(k, []), np.int64) for k in ("lip_upper", "lip_lower")])
    mouth_y = float(R.vertices[lips, 1].mean())
    why = (f"the jaw may sit on the wrong dots: the lips' lower edge in the images is {shift:+.1f} px from where "
           "the followed jaw puts it")
    return {str(int(v)): why for v in coarse if R.vertices[int(v), 1] < mouth_y and tpl.kinds[int(v)] != "lip_corner"}


def _blurred(m: np.ndarray, sigma: float) -> np.ndarray:
    from ..registration.dots import gaussian

    return gaussian(m, sigma)


def _rigid_score(session, maps: dict, X: np.ndarray, vis: np.ndarray) -> float:
    from ..registration.dots import bilinear

    return float(sum(bilinear(maps[cam.name], cam.project(X[vis[c]])[0]).sum()
                     for c, cam in enumerate(session.cams) if vis[c].any()))


def align_rigidly(session, X: np.ndarray, vis: np.ndarray, maps: dict, sigma_px: float = 1.5):
    """The rigid motion (4, 4) of points ``X`` (N, 3) (seen where ``vis`` (C, N)) that lands them on the most
    dot strength: a grid over head turns (yaw ±30°, pitch ±20°, roll ±10°, about their centroid) on
    blurred maps, then translations (±1.5 cm), then a local refinement on sharper maps."""
    from scipy.optimize import minimize
    from scipy.spatial.transform import Rotation

    from ..geometry.rigid import apply, homogeneous

    c0 = X.mean(0)
    pivots = [c0, c0 + np.array([0.0, -0.06, -0.09])]   # the face's centre, and the neck (a head turns about it)
    pivot = [c0]

    def T_of(p):
        Rm = Rotation.from_rotvec(np.radians(p[:3])).as_matrix()
        return homogeneous(Rm, pivot[0] + p[3:] - Rm @ pivot[0])

    def score(p, mp):
        return _rigid_score(session, mp, apply(T_of(p), X), vis)
    wide = {k: _blurred(m, 2.0 * sigma_px) for k, m in maps.items()}
    best, best_piv = np.zeros(6), c0
    best_s = score(best, wide)
    for pv in pivots:
        pivot[0] = pv
        for yaw in np.arange(-30, 31, 5.0):
            for pitch in np.arange(-20, 21, 5.0):
                for roll in (-10.0, -5.0, 0.0, 5.0, 10.0):
                    p = np.array([pitch, yaw, roll, 0, 0, 0])
                    sc = score(p, wide)
                    if sc > best_s:
                        best, best_s, best_piv = p, sc, pv
    pivot[0] = best_piv
    for step, span in ((0.005, 0.025), (0.00125, 0.005)):
        for axis in (0, 1, 2, 0, 1, 2):
            centre = best.copy()
            for d in np.arange(-span, span + 1e-9, step):
                p = centre.copy()
                p[3 + axis] += d
                sc = score(p, wide)
                if sc > best_s:
                    best, best_s = p, sc
    sharp = {k: _blurred(m, sigma_px) for k, m in maps.items()}
    scale = np.array([1.0, 1.0, 1.0, 1e-3, 1e-3, 1e-3])      # degrees and millimetres
    res = minimize(lambda q: -score(q * scale, sharp), best / scale, method="Powell",
                   options={"xtol": 0.05, "ftol": 1e-4, "maxfev": 600})
    p = res.x * scale if -res.fun >= score(best, sharp) else best
    return T_of(p)


def with_the_neck(session, tpl, R, moved: np.ndarray, dots: np.ndarray, maps: dict, sigma_px: float = 1.5,
                  bottoms=(0.75, 0.5, 0.25, 0.0), tops=(0.0, 0.25, 0.5)) -> np.ndarray:
    """The reference's vertices moved rigidly with the head (``moved``), the neck twisting less towards its
    base: below a height ``f`` of the way down the template's ``throat`` and ``neck`` regions the head's
    motion is blended with the reference's own position, its weight falling linearly with height from 1
    there to ``b`` at the lowest vertex; ``f`` of ``tops`` and ``b`` of ``bottoms`` the pair whose neck
    fiducials land on the most dot strength (2 % more than with the head's motion alone; a head
    turn leaves the base of the neck where it was; without the blend its dots are carried 1.5-3 cm off and
    snap onto their neighbours). Without those regions, ``moved``."""
    lower = np.unique(np.concatenate([np.asarray(tpl.regions.get(k, []), np.int64) for k in ("neck", "throat")]))
    lower = np.intersect1d(lower, dots)
    if len(lower) < 4:
        return moved
    y = R.vertices[:, 1]
    top, bottom = float(y[lower].max()), float(y.min())
    if top - bottom < 1e-3:
        return moved
    blurred = {k: _blurred(m, sigma_px) for k, m in maps.items()}
    best, best_s = moved, _rigid_score(session, blurred, moved[lower], R.visible[:, lower])
    for f in tops:
        start = top - f * (top - bottom)
        fall = np.clip((start - y) / (start - bottom), 0.0, 1.0)[:, None]
        for b in bottoms:
            w = 1.0 - (1.0 - b) * fall
            cand = w * moved + (1.0 - w) * R.vertices
            sc = _rigid_score(session, blurred, cand[lower], R.visible[:, lower])
            if sc > best_s * 1.02:
                best, best_s = cand, sc
    return best


def follow_dots(session, tpl, R, maps: dict, search_px: float, rounds: int = 8):
    """The template of the reference ``R`` carried onto this expression by its dots: a rigid alignment
    (:func:`align_rigidly`; the neck blended, :func:`with_the_neck`), then rounds in the spirit of the
    progressive snap (paper §4.1): every
    fiducial not yet placed starts from its prediction corrected by the placed fiducials round it on the
    template mesh (:func:`~mifacerf.registration.snap.predict_from_neighbours`, so the mouth's opening
    separates the jaw from the upper lip), snaps to the nearest dot peak within ``search_px`` in every
    view that sees it, and is placed where two or more views agree to 1 px — until no point joins.
    The other vertices follow their placed neighbours the same way. Returns (V (T, 3),
    {"visible": (C, T), "snapped": ids, "rigid": (4, 4)})."""
    from ..geometry.rigid import apply
    from ..geometry.triangulate import triangulate
    from ..registration.snap import dot_graph, predict_from_neighbours, two_rings
    from ..geometry.visibility import Visibility

    dots = tpl.dot_ids[R.status[tpl.dot_ids] == 1]
    vis = Visibility(tpl.triangles, tpl.n_vertices, tol=max(0.5 * centre_footprint(session.cams), 5e-4))
    T = align_rigidly(session, R.vertices[dots], R.visible[:, dots], maps)
    pred = with_the_neck(session, tpl, R, apply(T, R.vertices), dots, maps)
    nb = dot_graph(tpl.n_vertices, tpl.triangles, tpl.is_dot)
    rings2 = two_rings(nb)
    X = pred.copy()
    in_S = np.zeros(tpl.n_vertices, bool)
    taken = [set() for _ in session.cams]
    fp = centre_footprint(session.cams)
    # points near their start first (a wrong dot is never nearer than the right one's neighbour), then
    # farther, each step repeated while points join
    shifts = [f * search_px for f in (0.35, 0.5, 0.75, 1.0, 1.5, 2.0) for _ in range(rounds // 4 + 1)]
    for shift in shifts:
        rest = dots[~in_S[dots]]
        if rest.size == 0:
            break
        start = predict_from_neighbours(pred, X, in_S, rest, nb, rings2) if in_S.any() else pred[rest]
        Xm = X.copy()
        Xm[rest] = start
        visible = vis(Xm, session.cams, min_cos=0.2)
        uv = np.full((len(session.cams), len(rest), 2), np.nan)
        for c, cam in enumerate(session.cams):
            pk, val = peak_near(maps[cam.name], cam.project(start)[0], search_px)
            good = visible[c, rest] & (val >= 0.25) & np.isfinite(pk).all(1)
            uv[c, good] = pk[good]
        tr = triangulate(session.cams, uv, max_error=1.0)
        ok = tr.ok & (tr.max_error <= 1.0) & (np.linalg.norm(tr.points - start, axis=1) < shift * fp)
        # one image dot, one template point: the first to claim a peak keeps it
        for k in np.flatnonzero(ok):
            keys = [(c, tuple(np.round(uv[c, k], 2))) for c in range(len(session.cams)) if tr.used[c, k]]
            if any(key in taken[c] for c, key in keys):
                ok[k] = False
                continue
            for c, key in keys:
                taken[c].add(key)
        if not ok.any():
            continue
        X[rest[ok]] = tr.points[ok]
        in_S[rest[ok]] = True
    others = np.flatnonzero(~in_S)
    if in_S.any() and others.size:
        X[others] = predict_from_neighbours(pred, X, in_S, others, nb, rings2)
    return X, {"visible": vis(X, session.cams, min_cos=0.2), "snapped": np.flatnonzero(in_S), "rigid": T}


def _template_as_registered(session, tpl):
    """The template standing in for a registered neutral (positions as placed, visibility ray-traced)."""
    from types import SimpleNamespace

    from ..geometry.visibility import Visibility

    vis = Visibility(tpl.triangles, tpl.n_vertices, tol=max(0.5 * centre_footprint(session.cams), 5e-4))
    return SimpleNamespace(vertices=tpl.vertices.copy(), visible=vis(tpl.vertices, session.cams, min_cos=0.3),
                           status=np.ones(tpl.n_vertices, np.int8), teeth=np.stack([np.eye(4)] * 2),
                           head_pose=np.eye(4))


def _iris_from_template(tpl, side: str, R, V: np.ndarray, n: int = 24) -> np.ndarray | None:
    """(n, 3) the limbus of eye ``side`` looking forward (+Z of the head), moved with the morph (nearest vertex)."""
    eye = tpl.eyes.get(side) or {}
    if "centre" not in eye or "iris_radius" not in eye:
        return None
    H = np.asarray(R.head_pose, np.float64)
    c = H[:3, :3] @ np.asarray(eye["centre"], np.float64) + H[:3, 3]
    k = int(np.argmin(np.linalg.norm(R.vertices - c, axis=1)))
    g = H[:3, :3] @ np.array([0.0, 0.0, 1.0])
    c = c + (V[k] - R.vertices[k]) + float(eye.get("iris_depth", 0.0)) * g
    a = np.cross(g, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(g, a)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return c + float(eye["iris_radius"]) * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)


def _dense(P: np.ndarray, step: float = 4e-4) -> np.ndarray:
    """A 3-D polyline resampled about every ``step`` metres (a rotoscoped curve has a vertex every few px)."""
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    if s[-1] <= 0:
        return P
    t = np.linspace(0, s[-1], max(2, int(np.ceil(s[-1] / step)) + 1))
    return np.stack([np.interp(t, s, P[:, k]) for k in range(3)], 1)


def _dot_spacing(tpl) -> float:
    from scipy.spatial import cKDTree

    D = tpl.vertices[tpl.dot_ids]
    return float(np.median(cKDTree(D).query(D, 2)[0][:, 1])) if len(D) > 2 else 0.01
