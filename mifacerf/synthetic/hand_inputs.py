"""The synthetic "user": the hand-made registration inputs, made as a person would make them.

A real user of the pipeline builds a template on the neutral expression, places ~18
coarse points per expression in a 3-D point editor and rotoscopes the lips, the
eyelids and the irises in at least two views (paper §3, §4.1, §4.2). For the synthetic
subject those inputs are derived from the ground truth and then perturbed the way
clicking perturbs them: every 2-D click is the true projection plus Gaussian noise of
``click_sigma`` pixels per axis (0.7 px: about one pixel of radial error), and every 3-D
point the user places is *triangulated from such clicks* in the views where the point is
visible (so its error is what ~1 px clicking gives, larger in depth than across).

Written into the capture folder (never into ``truth/``)::

    CAPTURE/hand/template.json              the template, positions as placed on the neutral
    CAPTURE/hand/coarse_points.json         per expression: clicks and triangulated 3-D position
    CAPTURE/hand/rotoscope/<expression>.json  polylines, marked points, where the eyes look

Formats: docs/registration.md. Only the neutral's truth enters ``template.json``; every
other expression contributes only clicks (coarse points, rotoscoped curves and points). The template's
extensions (scalp, ears, neck; :mod:`.template_extensions`) are placed like every other vertex, from
clicks drawn apart from the face's (the face's hand inputs do not depend on them);
:func:`rewrite_template` gives an existing capture a template with (or without) them.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..formats.files import write_json_atomic
from ..geometry.footprint import centre_footprint
from ..rig import Rig

CLICK_SIGMA = 0.7        #: pixels per axis
CURVE_STEP_PX = 3.0      #: spacing of the user's polyline vertices
IRIS_SAMPLES = 24


@dataclass
class TruthExpression:
    """What the synthetic user looks at for one expression (truth; never written as such).

    ``template_vertices`` (T, 3); ``mesh`` (vertices (V, 3), faces (F, 3)) the surface (skin, teeth;
    not the eyeballs, on which the lids and the irises lie) used to decide which views see a point; ``irises`` {"L"/"R": (centre (3,), normal (3,), radius)};
    ``lower_teeth_point`` (3,) the marked point on the lower teeth; ``eyes_look_at`` "forward"
    when the subject looks straight ahead (the user was told so), else None.
    """

    name: str
    template_vertices: np.ndarray
    mesh: tuple
    irises: dict = field(default_factory=dict)
    lower_teeth_point: np.ndarray | None = None
    eyes_look_at: str | None = None


_SCENES: dict = {}


def _visibility(rig: Rig, truth: TruthExpression, points: np.ndarray, min_cos: float = 0.25) -> np.ndarray:
    """(C, N) which cameras see each point (ray-traced against the truth surface, not grazing)."""
    from ..geometry.meshscene import MeshScene

    V, F = truth.mesh
    key = id(truth)
    if _SCENES.get("key") != key:        # one ray-casting scene per expression, reused
        _SCENES.clear()
        _SCENES.update(key=key, scene=MeshScene(V, F), normals=None)
    scene = _SCENES["scene"]
    vis = np.zeros((len(rig.cameras), len(points)), bool)
    normals = _point_normals(V, F, points)
    for c, cam in enumerate(rig.cameras):
        v = scene.visible_from(points, cam, tol=5e-4)
        d = cam.centre - points
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        cosv = np.einsum("ij,ij->i", d, normals)
        vis[c] = v & ((cosv > min_cos) | ~np.isfinite(cosv))
    return vis


def _point_normals(V, F, P):
    """Normal of the nearest mesh vertex's one-ring (area weighted); NaN if far from the mesh."""
    from scipy.spatial import cKDTree

    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], n)
    vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-30)
    d, i = cKDTree(V).query(P)
    out = vn[i]
    out[d > 0.004] = np.nan
    return out


def _click(rig: Rig, X: np.ndarray, vis: np.ndarray, rng, sigma: float) -> dict:
    """Noisy clicks {camera: (N, 2)} of points X (N, 3) in the cameras that see them (NaN elsewhere)."""
    out = {}
    for c, cam in enumerate(rig.cameras):
        uv, _ = cam.project(X)
        uv = uv + rng.normal(0.0, sigma, uv.shape)
        uv[~vis[c]] = np.nan
        out[cam.name] = uv
    return out


def _place(rig: Rig, X: np.ndarray, vis: np.ndarray, rng, sigma: float, max_views: int = 6) -> np.ndarray:
    """3-D points as the user's tool places them: triangulated from noisy clicks; points seen by
    fewer than two views get an isotropic error of the same size (sigma pixel footprints)."""
    from ..geometry.triangulate import triangulate

    clicks = _click(rig, X, vis, rng, sigma)
    uv = np.stack([clicks[c.name] for c in rig.cameras])
    tr = triangulate(rig.cameras, uv)
    out = np.where(tr.ok[:, None], tr.points, np.nan)
    bad = ~tr.ok
    if bad.any():
        fp = centre_footprint(rig.cameras)
        out[bad] = X[bad] + rng.normal(0.0, sigma * fp, (bad.sum(), 3))
    return out


def _curve_views(rig: Rig, P: np.ndarray, vis: np.ndarray, k: int = 3) -> list[str]:
    """The views a rotoscoper picks for a curve P (n, 3): among views seeing most of it, the pair whose
    viewing directions differ most *across* the curve (so the two silhouettes fix its depth), plus
    the next best view (``k`` = 3)."""
    names = [c.name for c in rig.cameras]
    score = vis.mean(1)
    cand = [i for i in np.argsort(-score, kind="stable") if score[i] > 0.6]
    if len(cand) < 2:
        return []
    chord = P[-1] - P[0]
    chord = chord / max(np.linalg.norm(chord), 1e-12)
    q = []
    for i in range(len(names)):
        d = rig.cameras[i].centre - P.mean(0)
        d /= np.linalg.norm(d)
        d = d - (d @ chord) * chord
        q.append(d / max(np.linalg.norm(d), 1e-12))
    best, pair = -1.0, None
    for a in cand:
        for b in cand:
            if b <= a:
                continue
            ang = np.arccos(np.clip(q[a] @ q[b], -1, 1))
            val = ang * min(score[a], score[b])
            if val > best + 1e-9:
                best, pair = val, (a, b)
    chosen = list(pair)
    for i in cand:
        if len(chosen) >= k:
            break
        if i not in chosen:
            chosen.append(i)
    return [names[i] for i in chosen]


def _densify(P: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    if s[-1] <= 0:
        return P[:1]
    t = np.linspace(0, s[-1], max(2, int(np.ceil(s[-1] / step)) + 1))
    return np.stack([np.interp(t, s, P[:, k]) for k in range(P.shape[1])], 1)


def _polyline(cam, P3: np.ndarray, rng, sigma: float, closed: bool = False, min_points: int = 12) -> list:
    """A rotoscoped polyline: the curve's projection, resampled every CURVE_STEP_PX (at least
    ``min_points`` vertices round a closed curve), clicked with noise."""
    if closed:
        P3 = np.concatenate([P3, P3[:1]])
    dense = _densify(P3, 2e-4)
    uv, _ = cam.project(dense)
    uv = uv[np.isfinite(uv).all(1)]
    length = np.linalg.norm(np.diff(uv, axis=0), axis=1).sum()
    step = min(CURVE_STEP_PX, length / min_points) if closed else CURVE_STEP_PX
    poly = _densify(uv, max(step, 0.25))
    if closed:
        poly = poly[:-1]
    poly = poly + rng.normal(0.0, sigma, poly.shape)
    return np.round(poly, 3).tolist()


def iris_circle(centre, normal, radius, n: int = IRIS_SAMPLES) -> np.ndarray:
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(normal, [0.0, 1.0, 0.0])
    if np.linalg.norm(a) < 1e-6:
        a = np.cross(normal, [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.asarray(centre) + radius * (np.cos(t)[:, None] * a + np.sin(t)[:, None] * b)


def make_hand_inputs(cap_dir: str | os.PathLike, template: dict, truths: list[TruthExpression], rig: Rig,
                     seed: int = 0, click_sigma: float = CLICK_SIGMA, neutral: str | None = None) -> Path:
    """Write ``CAP_DIR/hand/`` from a ``mifacerf.template/1`` dict whose positions are the neutral's truth
    and the per-expression truth the user looks at. Returns the hand folder."""
    from ..geometry.margins import margins_from_holes
    from ..geometry.triangulate import triangulate

    rng = np.random.default_rng(seed + 8111)
    hand = Path(cap_dir) / "hand"
    (hand / "rotoscope").mkdir(parents=True, exist_ok=True)
    names = [c.name for c in rig.cameras]
    by_name = {t.name: t for t in truths}
    neutral = neutral or ("neutral" if "neutral" in by_name else truths[0].name)
    tn = by_name[neutral]
    fp = centre_footprint(rig.cameras)
    kinds = [v["kind"] for v in template["vertices"]]
    vnames = [v.get("name", "") for v in template["vertices"]]

    # ---- template: every vertex placed by the user on the neutral (the extensions' with clicks of their own,
    # so the face's hand inputs are the same with or without them)
    T = np.asarray(tn.template_vertices, np.float64)
    ext = np.zeros(len(T), bool)
    for e in (template.get("extensions") or {}).values():
        ext[np.asarray(e["vertices"], np.int64)] = True
    placed = np.empty_like(T)
    placed[~ext] = _place(rig, T[~ext], _visibility(rig, tn, T[~ext]), rng, click_sigma)
    if ext.any():
        placed[ext] = _place(rig, T[ext], _visibility(rig, tn, T[ext]), np.random.default_rng(seed + 8112),
                             click_sigma)
    tpl = json.loads(json.dumps(template))
    for v, p in zip(tpl["vertices"], placed):
        v["position"] = np.round(p, 7).tolist()
    for key, t in (tpl.get("teeth") or {}).items():   # strips placed in a reference view: a small offset
        off = rng.normal(0.0, click_sigma * fp, 3)
        t["vertices"] = np.round(np.asarray(t["vertices"], np.float64) + off, 7).tolist()
    for key, eye in (tpl.get("eyes") or {}).items():
        eye["centre"] = np.round(np.asarray(eye["centre"], np.float64) + rng.normal(0.0, click_sigma * fp, 3),
                                 7).tolist()
    tpl["made_by"] = "mifacerf synthetic user (truth of the neutral + ~1 px clicking error)"
    write_json_atomic(hand / "template.json", tpl)

    # ---- coarse points: clicked in every view that sees them, triangulated by the tool
    coarse = np.asarray(template.get("coarse_points", []), np.int64)
    entries = {}
    for t in truths:
        X = np.asarray(t.template_vertices, np.float64)[coarse]
        v = _visibility(rig, t, X)
        clicks = _click(rig, X, v, rng, click_sigma)
        uv = np.stack([clicks[n] for n in names])
        tr = triangulate(rig.cameras, uv)
        e = {}
        for j, vid in enumerate(coarse):
            e[str(int(vid))] = {
                "clicks": {n: np.round(clicks[n][j], 3).tolist() for n in names if np.isfinite(clicks[n][j]).all()},
                "position": np.round(tr.points[j], 7).tolist() if tr.ok[j] else None,
            }
        entries[t.name] = e
    write_json_atomic(hand / "coarse_points.json", {
        "format": "mifacerf.coarse_points", "version": 1, "coarse_points": coarse.tolist(),
        "click_sigma_px": click_sigma, "expressions": entries})

    # ---- rotoscoping: curves in the two views that see them best, the marked lower-teeth point
    margins = margins_from_holes(template.get("holes") or {}, kinds)
    head_points = {nm: i for i, nm in enumerate(vnames) if nm in ("ear_L", "ear_R", "nose_bridge")
                   and i not in set(coarse.tolist())}
    for t in truths:
        V = np.asarray(t.template_vertices, np.float64)
        curves, points = {}, {}
        for cname, ids in margins.items():
            P = V[np.asarray(ids, np.int64)]
            v = _visibility(rig, t, P, min_cos=0.0)
            views = _curve_views(rig, P, v)
            if len(views) >= 2:
                curves[cname] = {n: _polyline(rig.camera(n), P, rng, click_sigma) for n in views}
        for side, (c, nrm, r) in (t.irises or {}).items():
            c = np.asarray(c, np.float64)
            nrm = np.asarray(nrm, np.float64)
            circ = iris_circle(c, nrm, r)
            pts = np.concatenate([c[None], circ]) + 0.0005 * nrm[None]
            v = _visibility(rig, t, pts, min_cos=-2.0)
            cosines = np.array([float(np.dot(cam.centre - c, nrm) / np.linalg.norm(cam.centre - c))
                                for cam in rig.cameras])
            seen = (v.mean(1) >= 0.4) & (cosines > 0.3)
            views = [names[i] for i in np.argsort(-cosines) if seen[i]][:2]   # the most direct views
            if len(views) >= 2:
                curves[f"iris_{side}"] = {n: _polyline(rig.camera(n), circ, rng, click_sigma, closed=True)
                                          for n in views}
        marks = {name: V[int(vid)] for name, vid in head_points.items()}
        if t.lower_teeth_point is not None:
            marks["lower_teeth"] = np.asarray(t.lower_teeth_point, np.float64)
        for pname, X in marks.items():
            v = _visibility(rig, t, X[None], min_cos=0.1)
            if v.sum() >= 2:
                clicks = _click(rig, X[None], v, rng, click_sigma)
                points[pname] = {n: np.round(clicks[n][0], 3).tolist() for n in names
                                 if np.isfinite(clicks[n][0]).all()}
        write_json_atomic(hand / "rotoscope" / f"{t.name}.json", {
            "format": "mifacerf.rotoscope", "version": 1, "expression": t.name, "curves": curves,
            "points": points, "eyes_look_at": t.eyes_look_at})
    return hand


# --------------------------------------------------------------------------------- the synthetic subject
def lower_teeth_mark(strip_vertices: np.ndarray) -> int:
    """The strip vertex a user marks on the lower teeth: the incisal edge nearest the midline, in front."""
    V = np.asarray(strip_vertices, np.float64)
    top = V[:, 1] >= np.median(V[:, 1])           # incisal edges (the strip alternates edge / gum line)
    score = np.abs(V[:, 0]) - 0.5 * V[:, 2] + np.where(top, 0.0, 1.0)
    return int(np.argmin(score))


def iris_of(part_transform: np.ndarray, rest_centre) -> tuple:
    """(centre, normal, radius) of the limbus (the visible iris boundary) of an eye part whose
    eyeball centre is ``rest_centre`` in the part's rest frame (looking along +Z there)."""
    from . import parts as PT

    beta = PT.IRIS_ANGLE
    r = float(PT.eyeball_radius(beta))
    R, t = part_transform[:3, :3], part_transform[:3, 3]
    g = R @ np.array([0.0, 0.0, 1.0])
    centre = R @ (np.asarray(rest_centre, np.float64) + np.array([0.0, 0.0, r * np.cos(beta)])) + t
    return centre, g, r * np.sin(beta)


def _user_template(subject) -> dict:
    """``subject.template`` as the JSON dict the synthetic user writes (lower-teeth mark, iris sizes, dot
    radius added), positions still the neutral's truth."""
    from . import parts as PT

    template = json.loads(subject.template.to_json())
    lower = (template.get("teeth") or {}).get("lower")
    if lower is not None:
        lower["mark"] = lower_teeth_mark(lower["vertices"])
    beta = PT.IRIS_ANGLE
    r = float(PT.eyeball_radius(beta))
    for eye in (template.get("eyes") or {}).values():
        eye["iris_radius"] = r * float(np.sin(beta))
        eye["iris_depth"] = r * float(np.cos(beta))
    template["dot_radius"] = float(getattr(subject, "dot_radius", 0.0015))
    return template


def _truth_expression(subject, e, pose, lower: dict | None) -> TruthExpression:
    """What the synthetic user looks at in expression ``e`` (its ``pose``)."""
    occluders = [(pose.skin_vertices, subject.skin_faces)]
    for name in ("teeth_upper", "teeth_lower"):   # eyeballs left out: the lids rest on them
        if name in pose.parts:
            occluders.append((pose.parts[name].vertices, pose.parts[name].faces))
    Vs, Fs, off = [], [], 0
    for V, F in occluders:
        Vs.append(np.asarray(V, np.float64))
        Fs.append(np.asarray(F, np.int64) + off)
        off += len(V)
    irises = {}
    for name, side in (("eye_left", "L"), ("eye_right", "R")):
        if name in pose.parts and pose.parts[name].transform is not None:
            irises[side] = iris_of(pose.parts[name].transform, subject.eye_centres[name])
    ltp = None
    if lower is not None and "teeth_lower" in pose.parts:
        T = pose.parts["teeth_lower"].transform
        p = np.asarray(subject.template.teeth["lower"]["vertices"], np.float64)[lower["mark"]]
        ltp = T[:3, :3] @ p + T[:3, 3]
    ctrl = list(getattr(subject, "control_names", []))
    gaze = [abs(float(e.params[ctrl.index(k)])) for k in ("gaze_yaw", "gaze_pitch") if k in ctrl]
    look = "forward" if gaze and max(gaze) < 1e-6 else None
    return TruthExpression(e.name, np.asarray(pose.template_vertices, np.float64),
                           (np.concatenate(Vs), np.concatenate(Fs)), irises, ltp, look)


def write_hand_inputs(cap_dir, subject, expressions, poses, rig: Rig, seed: int = 0,
                      click_sigma: float = CLICK_SIGMA) -> Path:
    """The synthetic user's hand inputs for a synthesised capture (called by ``mifacerf synth``).

    ``expressions``: the subject's ``Expression(name, category, params)``; ``poses[name]`` its
    ``Pose``. Only the neutral's truth enters the template; every expression gets clicks.
    """
    template = _user_template(subject)
    lower = (template.get("teeth") or {}).get("lower")
    truths = [_truth_expression(subject, e, poses[e.name], lower) for e in expressions]
    neutral = next((e.name for e in expressions if e.category == "neutral"), expressions[0].name)
    return make_hand_inputs(cap_dir, template, truths, rig, seed=seed, click_sigma=click_sigma, neutral=neutral)


def rewrite_template(cap_dir, subject, rig: Rig, seed: int = 0, click_sigma: float = CLICK_SIGMA) -> Path:
    """Rewrite ``CAP_DIR/hand/template.json`` for ``subject.template`` (the procedural subject's, with or
    without extensions, e.g. another neck cut), keeping what the user placed in the existing file — every
    face vertex, the teeth strips, the eyes — and placing the new template's extension vertices on the
    neutral's truth with the clicks :func:`make_hand_inputs` draws for them. Coarse points and rotoscoping
    (face vertex ids) stay valid. Returns the file."""
    from .expressions import default_params
    from .presets import Expression

    path = Path(cap_dir) / "hand" / "template.json"
    old = json.loads(path.read_text())
    new = _user_template(subject)
    n_old, ext_new = len(old["vertices"]), np.zeros(len(new["vertices"]), bool)
    for e in (new.get("extensions") or {}).values():
        ext_new[np.asarray(e["vertices"], np.int64)] = True
    old_ext = np.zeros(n_old, bool)
    for e in (old.get("extensions") or {}).values():
        old_ext[np.asarray(e["vertices"], np.int64)] = True
    face_old = [v for v, x in zip(old["vertices"], old_ext) if not x]
    face_new = [v for v, x in zip(new["vertices"], ext_new) if not x]
    if [(v["kind"], v.get("name", "")) for v in face_old] != [(v["kind"], v.get("name", "")) for v in face_new] or \
            old_ext.any() and not (np.flatnonzero(~old_ext) == np.arange(len(face_old))).all():
        raise ValueError(f"{path}: its face vertices are not the subject template's (kinds/names differ): "
                         "this capture was made from another subject or template")
    for v, o in zip(face_new, face_old):
        v["position"] = o["position"]
    for key in ("teeth", "eyes", "dot_radius"):
        if key in old:
            new[key] = old[key]
    if ext_new.any():
        pose = subject.pose(default_params(), textures=False)
        truth = _truth_expression(subject, Expression("neutral", "neutral", default_params()), pose, None)
        X = truth.template_vertices[ext_new]
        placed = _place(rig, X, _visibility(rig, truth, X), np.random.default_rng(seed + 8112), click_sigma)
        for v, p in zip(np.asarray(new["vertices"], object)[ext_new], placed):
            v["position"] = np.round(p, 7).tolist()
    new["made_by"] = old.get("made_by", "mifacerf synthetic user (truth of the neutral + ~1 px clicking error)")
    write_json_atomic(path, new)
    return path
