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
other expression contributes only clicks (coarse points, rotoscoped curves and points).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..capture_folder import write_json_atomic
from ..rig import Rig

CLICK_SIGMA = 0.7        #: pixels per axis
CURVE_STEP_PX = 3.0      #: spacing of the user's polyline vertices
IRIS_SAMPLES = 24


@dataclass
class TruthExpression:
    """What the synthetic user looks at for one expression (truth; never written as such).

    ``template_vertices`` (T, 3); ``mesh`` (vertices (V, 3), faces (F, 3)) the visible surface
    used to decide which views see a point; ``irises`` {"L"/"R": (centre (3,), normal (3,), radius)};
    ``lower_teeth_point`` (3,) the marked point on the lower teeth; ``eyes_look_at`` "forward"
    when the subject looks straight ahead (the user was told so), else None.
    """

    name: str
    template_vertices: np.ndarray
    mesh: tuple
    irises: dict = field(default_factory=dict)
    lower_teeth_point: np.ndarray | None = None
    eyes_look_at: str | None = None


def _visibility(rig: Rig, truth: TruthExpression, points: np.ndarray, min_cos: float = 0.25) -> np.ndarray:
    """(C, N) which cameras see each point (ray-traced against the truth surface, not grazing)."""
    from ..rendering.meshscene import MeshScene

    V, F = truth.mesh
    scene = MeshScene(V, F)
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
    from ..registration.triangulate import triangulate

    clicks = _click(rig, X, vis, rng, sigma)
    uv = np.stack([clicks[c.name] for c in rig.cameras])
    tr = triangulate(rig.cameras, uv)
    out = np.where(tr.ok[:, None], tr.points, np.nan)
    bad = ~tr.ok
    if bad.any():
        fp = np.median([cam.pixel_footprint(np.linalg.norm(cam.centre)) for cam in rig.cameras])
        out[bad] = X[bad] + rng.normal(0.0, sigma * fp, (bad.sum(), 3))
    return out


def _best_views(vis: np.ndarray, names: list[str], k: int = 2) -> list[str]:
    """The ``k`` cameras that see most of a feature (ties: the earlier camera)."""
    score = vis.mean(1)
    order = np.argsort(-score, kind="stable")
    return [names[i] for i in order[:k] if score[i] > 0.5]


def _densify(P: np.ndarray, step: float) -> np.ndarray:
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0], np.cumsum(seg)])
    if s[-1] <= 0:
        return P[:1]
    t = np.linspace(0, s[-1], max(2, int(np.ceil(s[-1] / step)) + 1))
    return np.stack([np.interp(t, s, P[:, k]) for k in range(P.shape[1])], 1)


def _polyline(cam, P3: np.ndarray, rng, sigma: float, closed: bool = False) -> list:
    """A rotoscoped polyline: the curve's projection, resampled every CURVE_STEP_PX, clicked with noise."""
    if closed:
        P3 = np.concatenate([P3, P3[:1]])
    dense = _densify(P3, 2e-4)
    uv, _ = cam.project(dense)
    uv = uv[np.isfinite(uv).all(1)]
    poly = _densify(uv, CURVE_STEP_PX)
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
    """Write ``CAP_DIR/hand/`` from a canonical template dict (vertices = the neutral's truth) and the
    per-expression truth the user looks at. Returns the hand folder."""
    rng = np.random.default_rng(seed + 8111)
    hand = Path(cap_dir) / "hand"
    (hand / "rotoscope").mkdir(parents=True, exist_ok=True)
    names = [c.name for c in rig.cameras]
    by_name = {t.name: t for t in truths}
    neutral = neutral or ("neutral" if "neutral" in by_name else truths[0].name)
    tn = by_name[neutral]

    # ---- template: every vertex placed by the user on the neutral
    T = np.asarray(tn.template_vertices, np.float64)
    vis = _visibility(rig, tn, T)
    placed = _place(rig, T, vis, rng, click_sigma)
    tpl = dict(template)
    tpl["vertices"] = np.round(placed, 7).tolist()
    if tpl.get("lower_teeth_point") is not None:
        p = np.asarray(tpl["lower_teeth_point"], np.float64)[None]
        tpl["lower_teeth_point"] = np.round(_place(rig, p, np.zeros((len(names), 1), bool), rng,
                                                   click_sigma)[0], 7).tolist()
    for side, eye in (tpl.get("eyes") or {}).items():
        if "centre" in eye:
            c = np.asarray(eye["centre"], np.float64)[None]
            eye["centre"] = np.round(_place(rig, c, np.zeros((len(names), 1), bool), rng, click_sigma)[0],
                                     7).tolist()
    tpl["made_by"] = "mifacerf synthetic user (truth of the neutral + ~1 px clicking error)"
    write_json_atomic(hand / "template.json", tpl)

    # ---- coarse points: clicked in every view that sees them, triangulated by the tool
    coarse = np.asarray(template.get("coarse", []), np.int64)
    from ..registration.triangulate import triangulate

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
        "format": "mifacerf.coarse_points", "version": 1, "coarse": coarse.tolist(),
        "click_sigma_px": click_sigma, "expressions": entries})

    # ---- rotoscoping: curves in the two views that see them best, marked points
    margins = template.get("margins") or {}
    head_points = template.get("head_points") or {}
    for t in truths:
        V = np.asarray(t.template_vertices, np.float64)
        curves, points = {}, {}
        for cname, ids in margins.items():
            P = V[np.asarray(ids, np.int64)]
            v = _visibility(rig, t, P, min_cos=0.0)
            views = _best_views(v, names)
            if len(views) >= 2:
                curves[cname] = {n: _polyline(rig.camera(n), P, rng, click_sigma) for n in views}
        for side, (c, nrm, r) in (t.irises or {}).items():
            c = np.asarray(c, np.float64)
            v = _visibility(rig, t, c[None] + 0.0005 * np.asarray(nrm)[None], min_cos=0.2)
            views = [names[i] for i in np.flatnonzero(v[:, 0])]
            if len(views) >= 2:
                # the two views that look most directly at the iris
                dots = [float(np.dot(rig.camera(n).centre - c, nrm) / np.linalg.norm(rig.camera(n).centre - c))
                        for n in views]
                views = [views[i] for i in np.argsort(dots)[::-1][:2]]
                circ = iris_circle(c, nrm, r)
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
