"""Rendering accuracy against path-traced ground truth (the rendering issue's measurement).

Cases, drawn with a fresh seed (never the ones used while developing):

* **a** a captured expression seen by a capture camera;
* **b** a random linear blend of 2–3 captured expressions (Dirichlet weights), a capture
  camera; the truth is the subject at the same blend of parameter vectors;
* **c** a captured expression from a novel viewpoint between the cameras;
* **d** an out-of-set deformation: a random parameter vector (each control drawn on its
  own, so not a blend of the captured ones); the model gets only its template mesh
  (as performance capture would deliver it) and blends with the §5 weights; the same
  mesh rendered from the neutral expression's data only is the baseline, compared on
  the wrinkle regions (skin whose wrinkle activation is high).

PSNR on the face mask (:mod:`.masks`, kept for continuity: it scores only pixels the model fully
covers), and what the user sees: **composite PSNR** (render and truth each over the same plate,
the environment seen from the camera, on every pixel where either has coverage, so missing or
extra coverage is error), **silhouette IoU** (the render's alpha against the truth's), the
**uncovered** share of the truth's foreground (with a picture of where: red = missed, blue =
extra) and **where the composite error sits** (:func:`.metrics.error_regions`: the face mask, the
extensions — the truth's foreground outside it —, the silhouette band, extra coverage); per
environment; time per frame with a warm model
and its breakdown by stage. Every truth is path-traced as two halves of ``spp_truth``
with different seeds (:func:`.metrics.psnr_two_truths`): each case reports its truth's own
Monte Carlo noise floor and, beside the plain PSNR against the truth, the PSNR with
that noise subtracted (an estimate of the error against the noise-free truth).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..camera import ring_camera
from ..execution import Executor, worker_cached
from ..rendering.renderer import RenderStats
from .masks import classify_pixels, face_mask, triangle_mask
from .metrics import (REGIONS, composite_psnr, composite_psnr_two_truths, coverage_picture, error_regions, over, psnr,
                      psnr_two_truths, silhouette_iou, summary, uncovered)


@dataclass
class Case:
    kind: str
    label: str
    camera: object
    params: np.ndarray
    expression: object = None  # model input: name / weights dict
    mesh: np.ndarray | None = None
    results: dict = field(default_factory=dict)


def draw_cases(tr, model, rng, n: int = 2) -> list[Case]:
    """``tr``: TruthRenderer; ``model``: the model (its captured expressions); ``n`` cases per kind."""
    names = [e for e in model.expressions if e in tr.expressions]
    cams = model.cameras
    cases = []
    for _ in range(n):
        e = str(rng.choice(names))
        c = cams[int(rng.integers(len(cams)))]
        cases.append(Case("a", f"a:{e}@{c.name}", c, tr.expressions[e], expression=e))
    for _ in range(n):
        k = int(rng.integers(2, 4))
        chosen = list(rng.choice(names, size=k, replace=False))
        w = rng.dirichlet(np.ones(k))
        weights = {str(a): float(b) for a, b in zip(chosen, w)}
        c = cams[int(rng.integers(len(cams)))]
        cases.append(Case("b", "b:" + "+".join(f"{b:.2f}{a}" for a, b in weights.items()) + f"@{c.name}", c,
                          tr.blend(weights), expression=weights))
    for _ in range(n):
        e = str(rng.choice(names))
        yaw, pitch = float(rng.uniform(-30, 30)), float(rng.uniform(-7, 7))
        cam = ring_camera(cams, yaw, pitch)
        cases.append(Case("c", f"c:{e}@yaw{yaw:+.0f},pitch{pitch:+.0f}", cam, tr.expressions[e], expression=e))
    for _ in range(n):
        p = random_params(tr.subject, rng)
        c = cams[int(rng.integers(len(cams)))]
        # a model built without the template's extensions is given the face part (its vertices come first)
        mesh = tr.subject.pose(p, textures=False).template_vertices[:model.n_vertices]
        cases.append(Case("d", f"d:random#{len(cases)}@{c.name}", c, p, mesh=mesh))
    return cases


def random_params(subject, rng, spread: float = 0.6) -> np.ndarray:
    """An out-of-set parameter vector: each control drawn independently in ``spread`` of its range."""
    p = subject.params()
    for i, c in enumerate(subject.controls):
        lo, hi = c.lo, c.hi
        mid = c.default
        if "head" in c.name or "gaze" in c.name:
            p[i] = mid + rng.uniform(-0.3, 0.3) * (hi - lo) / 2
        elif rng.random() < 0.5:
            p[i] = mid + rng.uniform(0, spread) * (hi - mid)
    return p


def wrinkle_triangles(subject, params, threshold: float = 0.3) -> np.ndarray:
    """(F,) bool: skin triangles whose strongest wrinkle activation exceeds ``threshold``."""
    pose = subject.pose(params)
    if not pose.wrinkles:
        return np.zeros(len(subject.skin_faces), bool)
    act = np.max(np.stack([np.asarray(a) for a in pose.wrinkles.values()]), axis=0)
    return act[subject.skin_faces].max(axis=1) > threshold


def evaluate(out, model_path, envs=("sky", "interior", "gradient"), n: int = 2, seed: int = 20261122,
             spp_truth: int = 1024, spp: int = 4, size: int | None = None, progress: bool = True,
             pictures: Path | None = None, executor=None) -> dict:
    """Run every case under every environment (``progress``: a bar over them); returns a JSON-able report.

    ``executor`` (:mod:`mifacerf.execution`; default: this process) runs each (case, environment) as one
    unit (:func:`run_case`); the report lists them in the same order with the same truth seeds."""
    from ..imageio import write_png
    from ..pictures import grid
    from ..rendering.api import load_model
    from ..synthetic.truth_scene import TruthRenderer

    tr = TruthRenderer.from_synth(out)
    face = load_model(model_path)
    rng = np.random.default_rng(seed)
    cases = draw_cases(tr, face.model, rng, n)
    jobs = [(c, e) for c in cases for e in envs]
    tiles = []
    report = {"seed": seed, "spp_truth": spp_truth, "spp": spp, "envs": list(envs), "cases": []}
    seeds = [int(rng.integers(1 << 30)) for _ in jobs]   # one per job, drawn in the jobs' order as before
    units = [(case, env, seed_t, pictures is not None and i < 24) for i, ((case, env), seed_t) in
             enumerate(zip(jobs, seeds))]
    context = CaseContext(out, model_path, tr, face, spp_truth=spp_truth, spp=spp, size=size)
    for entry, case_pictures in (executor or Executor()).imap(run_case, units, context, desc="cases",
                                                              unit="case", progress=progress):
        report["cases"].append(entry)
        tiles += case_pictures
    by = {}
    for e in report["cases"]:
        by.setdefault(e["case"], []).append(e)
    report["summary"] = {k: {"psnr": summary([x["psnr"] for x in v]),
                             "psnr_noise_corrected": summary([x["psnr_noise_corrected"] for x in v]),
                             "psnr_composite": summary([x["psnr_composite"] for x in v]),
                             "psnr_composite_noise_corrected": summary([x["psnr_composite_noise_corrected"] for x in v]),
                             "silhouette_iou": summary([x["silhouette_iou"] for x in v]),
                             "uncovered": summary([x["uncovered"] for x in v]),
                             "error_share": {r: summary([x["regions"][r]["error_share"] for x in v]) for r in REGIONS},
                             "seconds": summary([x["seconds"] for x in v]),
                             **({"psnr_wrinkles": summary([x.get("psnr_wrinkles", np.nan) for x in v]),
                                 "psnr_wrinkles_neutral_only": summary([x.get("psnr_wrinkles_neutral_only", np.nan)
                                                                        for x in v])} if k == "d" else {})}
                         for k, v in by.items()}
    report["truth_noise_psnr"] = min(e["truth_noise_psnr"] for e in report["cases"])  # the noisiest truth
    if pictures is not None and tiles:
        pictures.parent.mkdir(parents=True, exist_ok=True)
        write_png(pictures, grid(tiles, 4))
    return report


class CaseContext:
    """What every unit of an evaluation shares: a synth output (its truth) and a model, and the run's settings
    as attributes (``spp_truth``, ``spp``, ``size``, ...).

    Pickled (sent to a worker) it keeps the folders instead of the truth renderer and the model; a worker
    opens them once (:func:`mifacerf.execution.worker_cached`) for all its units."""

    def __init__(self, out, model_path, tr=None, face=None, **settings):
        self.out, self.model_path, self._tr, self._face = str(out), str(model_path), tr, face
        self.__dict__.update(settings)

    def __getstate__(self):
        return {**self.__dict__, "_tr": None, "_face": None}

    def opened(self):
        """(TruthRenderer, FaceModel)."""
        if self._tr is None:
            from ..rendering.api import load_model
            from ..synthetic.truth_scene import TruthRenderer

            stamp = os.stat(Path(self.model_path) / "model.json").st_mtime_ns
            self._tr, self._face = worker_cached(("truth and model", self.out, self.model_path, stamp), lambda: (
                TruthRenderer.from_synth(self.out), load_model(self.model_path)))
        return self._tr, self._face


def run_case(context: CaseContext, unit: tuple) -> tuple[dict, list]:
    """One case under one environment, ``unit = (case, env, truth seed, picture?)`` → (report entry, its
    row of ``cases.png`` or [])."""
    from ..rendering.api import environment_plate

    case, env, seed_t, picture = unit
    tr, face = context.opened()
    cam = case.camera if context.size is None else case.camera.resized(context.size, context.size)
    halves = [tr.render(case.params, cam, env, spp=max(1, context.spp_truth // 2), seed=seed_t + k) for k in (0, 1)]
    truth = 0.5 * (halves[0] + halves[1])
    sc = tr.scene(face.environment(env))
    classes = classify_pixels(sc, cam, spp=4)
    modelled = face_mask(classes)
    mask = modelled & (truth[..., 3] > 0.999)
    stats = RenderStats()
    face.renderer.cache_frames = False   # time a real render, not the unchanged-frame cache
    face.render(case.expression, mesh=case.mesh, camera=cam, env=env, spp=context.spp)  # warm (kernels, fields)
    t0 = time.perf_counter()
    img = face.render(case.expression, mesh=case.mesh, camera=cam, env=env, spp=context.spp, stats=stats)
    seconds = time.perf_counter() - t0
    m = mask & (img[..., 3] > 0.999)
    err = psnr_two_truths(img, halves[0], halves[1], m)
    entry = {"case": case.kind, "label": case.label, "env": env, "psnr": err["psnr"],
             "psnr_noise_corrected": err["psnr_noise_corrected"], "truth_noise_psnr": err["noise_floor"],
             "coverage": float(m.sum() / max(mask.sum(), 1)), "seconds": seconds,
             "stages": {k: round(v, 4) for k, v in stats.times.items()}, "pixels": int(m.sum()),
             "fields": len(stats.fields_loaded)}
    plate = environment_plate(face.environment(env), cam)
    share, _ = uncovered(img[..., 3], truth[..., 3])
    comp = composite_psnr_two_truths(img, halves[0], halves[1], plate)
    entry.update({"psnr_composite": composite_psnr(img, truth, plate),
                  "psnr_composite_noise_corrected": comp["psnr_noise_corrected"],
                  "truth_noise_psnr_composite": comp["noise_floor"],
                  "silhouette_iou": silhouette_iou(img[..., 3], truth[..., 3]), "uncovered": share,
                  "regions": error_regions(img, truth, plate, modelled)})
    if case.kind == "d":
        wr = triangle_mask(classes, wrinkle_triangles(tr.subject, case.params)) & m
        neutral = _neutral_render(face, case, cam, env, context.spp)
        entry["wrinkle_pixels"] = int(wr.sum())
        if wr.sum() > 20:
            entry["psnr_wrinkles"] = psnr(img, truth, wr)
            entry["psnr_wrinkles_neutral_only"] = psnr(neutral, truth, wr)
        entry["psnr_neutral_only"] = psnr(neutral, truth, m & (neutral[..., 3] > 0.999))
    return entry, (case_tiles(img, truth, plate, entry, 192) if picture else [])


def case_tiles(img, truth, plate, entry: dict, size: int = 192) -> list:
    """One case's row of ``cases.png``: truth and render each over the plate (what the user sees), the
    composite's |error| on the scored pixels, and the coverage (grey both, red missed, blue extra)."""
    from ..pictures import error_map, label, tile8

    comp_t, comp_r = over(truth, plate), over(img, plate)
    scored = (img[..., 3] > 1e-3) | (truth[..., 3] > 1e-3)
    return [label(tile8(comp_t, size=size), f"truth {entry['label'][:28]}"),
            label(tile8(comp_r, size=size), f"render {entry['env']}"),
            label(tile8(error_map(comp_r, comp_t, 0.05, scored), size=size),
                  f"|error| {entry['psnr_composite']:.1f} dB (face {entry['psnr']:.1f})"),
            label(tile8(coverage_picture(img[..., 3], truth[..., 3]), size=size),
                  f"IoU {entry['silhouette_iou']:.3f}, red miss {100 * entry['uncovered']:.1f}%")]


def _neutral_render(face, case, cam, env, spp):
    """The target mesh rendered from the neutral expression's reflectance fields only (the baseline)."""
    target, _ = face.target(mesh=case.mesh)
    W = np.zeros((face.model.n_vertices, len(face.model.expressions)))
    W[:, face.model.expression_index(face.model.neutral)] = 1.0
    return face.renderer.render(target, W, cam, face.environment(env), spp=spp, parts=face.parts(mesh=case.mesh))


def view_angle(camera, cameras, centre) -> float:
    """Degrees between ``camera``'s direction from ``centre`` and the nearest of ``cameras``'."""
    d = camera.centre - centre
    dirs = np.array([c.centre - centre for c in cameras], np.float64)
    cos = dirs @ d / (np.linalg.norm(dirs, axis=1) * np.linalg.norm(d))
    return float(np.degrees(np.arccos(np.clip(cos.max(), -1.0, 1.0))))


def camera_off_the_rig(cameras, degrees: float = 30.0, side: float = 1.0):
    """A ring camera (:func:`mifacerf.camera.ring_camera`) ``degrees`` from the nearest capture camera,
    beyond the outermost one on the ``side`` (+1: +X, towards positive yaw; -1: the other) at that
    camera's pitch: found by bisection on the yaw."""
    from ..camera import cameras_focus

    centre = cameras_focus(cameras)
    d = np.array([c.centre - centre for c in cameras])
    yaws = np.degrees(np.arctan2(d[:, 0], d[:, 2]))
    k = int(np.argmax(side * yaws))
    pitch = float(np.degrees(np.arcsin(d[k, 1] / np.linalg.norm(d[k]))))
    lo, hi = float(yaws[k]), float(yaws[k]) + side * 90.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if view_angle(ring_camera(cameras, mid, pitch), cameras, centre) < degrees:
            lo = mid
        else:
            hi = mid
    yaw = 0.5 * (lo + hi)
    return ring_camera(cameras, yaw, pitch, name=f"yaw{yaw:+.1f}_pitch{pitch:+.1f}")


def novel_view_picture(out, model_path, picture, degrees: float = 30.0, expression: str | None = None,
                       env: str = "sky", spp_truth: int = 256, spp: int = 4, size: int = 256, seed: int = 0) -> dict:
    """truth | render | |error|, each over the environment's plate, for a view ``degrees`` off the nearest
    capture camera (:func:`camera_off_the_rig`) of a captured ``expression`` (default: the neutral); the
    error is shown on every pixel where either has coverage. Writes ``picture`` (PNG); returns the view and
    the numbers of a case (composite and face PSNR, IoU, uncovered, where the error sits)."""
    from ..imageio import write_png
    from ..pictures import error_map, grid, label, tile8
    from ..rendering.api import environment_plate, load_model
    from ..synthetic.truth_scene import TruthRenderer

    tr = TruthRenderer.from_synth(out)
    face = load_model(model_path)
    expression = expression or face.model.neutral
    cam = camera_off_the_rig(face.model.cameras, degrees).resized(size, size)
    params = tr.expressions[expression]
    halves = [tr.render(params, cam, env, spp=max(1, spp_truth // 2), seed=seed + k) for k in (0, 1)]
    truth = 0.5 * (halves[0] + halves[1])
    img = face.render(expression, camera=cam, env=env, spp=spp)
    plate = environment_plate(face.environment(env), cam)
    modelled = face_mask(classify_pixels(tr.scene(face.environment(env)), cam, spp=4))
    m = modelled & (truth[..., 3] > 0.999) & (img[..., 3] > 0.999)
    share, _ = uncovered(img[..., 3], truth[..., 3])
    res = {"camera": cam.name, "degrees": degrees, "expression": expression, "env": env,
           "psnr": psnr(img, truth, m), "psnr_composite": composite_psnr(img, truth, plate),
           "silhouette_iou": silhouette_iou(img[..., 3], truth[..., 3]), "uncovered": share,
           "regions": error_regions(img, truth, plate, modelled)}
    comp_t, comp_r = over(truth, plate), over(img, plate)
    scored = (img[..., 3] > 1e-3) | (truth[..., 3] > 1e-3)
    tiles = [label(tile8(comp_t), f"truth {expression}, {degrees:.0f} deg off the rig"),
             label(tile8(comp_r), f"render {env}"),
             label(tile8(error_map(comp_r, comp_t, 0.05, scored)),
                   f"|error| {res['psnr_composite']:.1f} dB, IoU {res['silhouette_iou']:.3f}")]
    Path(picture).parent.mkdir(parents=True, exist_ok=True)
    write_png(picture, grid(tiles, 3))
    return res
