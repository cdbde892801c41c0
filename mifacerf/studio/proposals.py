"""Hand inputs proposed by the studio, so the user verifies rather than clicks (beyond the paper).

* :func:`untuned_filter` — a dot filter before any registration (tuned on the template's fiducials if
  there is a template, else the prior yellow colour direction of :mod:`mifacerf.registration.dots`).
* :func:`propose_expression` — for an expression, from the nearest registered expression ``R`` (the
  one whose registered fiducials, projected into this expression's views, land on the most dot
  strength): the coarse points snapped to this expression's dots in each view where ``R`` saw them,
  triangulated; ``R``'s whole template carried by the coarse morph (:class:`~mifacerf.registration.morph.CoarseMorph`)
  from ``R``'s coarse points to those; the lip and eyelid margins, the head points and the lower-teeth
  mark projected from the morphed template into the views ``R``'s rotoscoping used (or the two views
  that see them most directly); the irises from ``R``'s curves moved with the morphed eye.
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
    from ..registration.morph import CoarseMorph
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
    uvR = np.stack([cam.project(R.vertices[coarse])[0] for cam in session.cams])      # (C, K, 2)
    clicks = np.full_like(uvR, np.nan)
    for c, cam in enumerate(session.cams):
        vis = R.visible[c, coarse]
        pk, val = peak_near(maps[cam.name], uvR[c], search)
        good = vis & (val >= 0.25) & np.isfinite(pk).all(1)
        # a non-dot coarse point (mouth corner, ear) has no dot: keep the reference's projection
        nodot = vis & ~tpl.is_dot[coarse]
        clicks[c, good] = pk[good]
        clicks[c, nodot] = uvR[c, nodot]
    tr = triangulate(session.cams, clicks, max_error=2.0)
    ok = tr.ok & (tr.max_error <= 2.0)
    state = {"coarse": {}, "rotoscope": {"curves": {}, "points": {}, "eyes_look_at": None}, "overrides": {}}
    for j, vid in enumerate(coarse):
        if ok[j]:
            state["coarse"][str(int(vid))] = {
                "clicks": {n: np.round(clicks[c, j], 3).tolist() for c, n in enumerate(session.names)
                           if tr.used[c, j]},
                "position": np.round(tr.points[j], 7).tolist()}
    # the whole template carried by the coarse morph from R's coarse points to the proposed ones
    cR = R.vertices[coarse]
    cE = np.where(ok[:, None], tr.points, np.nan)
    V = R.vertices.copy()
    usable = np.isfinite(cE).all(1)
    if usable.sum() >= 3:
        from ..registration.morph import mls_affine

        cE[~usable] = mls_affine(cR[usable], cE[usable], cR[~usable], k=6, eps=0.01) if (~usable).any() else cE[~usable]
        try:
            V = CoarseMorph(cR, cE, tpl.coarse_triangles)(R.vertices)
        except (ValueError, np.linalg.LinAlgError):
            V = R.vertices.copy()
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
        # carried by the morph's displacement of the nearest template vertex
        k = int(np.argmin(np.linalg.norm(R.vertices - pR, axis=1)))
        p = pR + (V[k] - R.vertices[k])
        views = [c for c in rot_src["points"].get("lower_teeth", {}) if c in session.names]
        if len(views) >= 2:
            state["rotoscope"]["points"]["lower_teeth"] = {
                c: np.round(session.camera(c).project(p[None])[0][0], 3).tolist() for c in views}
    state["rotoscope"]["eyes_look_at"] = rot_src.get("eyes_look_at")
    n_ok = int(ok.sum())
    return {"source": src, "state": state,
            "note": f"from {src}: {n_ok} of {len(coarse)} coarse points found on this expression's dots; "
                    f"{len(state['rotoscope']['curves'])} curves and {len(state['rotoscope']['points'])} marks "
                    "projected from the coarse morph"}


def _template_as_registered(session, tpl):
    """The template standing in for a registered neutral (positions as placed, visibility ray-traced)."""
    from types import SimpleNamespace

    from ..registration.visibility import Visibility

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
