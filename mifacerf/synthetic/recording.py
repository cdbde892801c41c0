"""Recording the synthetic performance: the multi-view video, its truth and the user's keyframe marks.

``record_performance(OUT, seconds)`` — what ``mifacerf synth OUT --performance SECONDS`` runs after
the light-stage capture:

* the trajectory (:func:`.performance.script`) is posed frame by frame and photographed by the
  capture rig's cameras (resized to the video resolution), synchronised, at ``fps``, under
  diffuse **studio lighting**: a dozen directional lights spread over the front of the subject
  (the paper's "several fresnel spotlights and bounce cards"), rendered with ray-traced shadows
  (:func:`render_lit`), so the video has no Monte-Carlo noise, only the pixel filter's
  anti-aliasing and a video camera's read and shot noise (:func:`sensor_noise`); the fiducial
  dots are left on;
* ``OUT/performance/`` gets the frames and the hand inputs (:mod:`mifacerf.formats.performance`);
* ``OUT/truth/performance/`` gets the truth: ``performance.json`` (controls, the script's events,
  keyframe choice) and ``frames.npz`` — ``params`` (N, P), ``template_vertices`` (N, T, 3), ``dots``
  (N, D, 3), ``head`` (N, 4, 4), ``eyes`` (N, 2, 4, 4) (left, right eyeball rest → world), ``jaw``
  (N, 4, 4). The full skin of any frame is ``subject.pose(params[f])``.

The synthetic user marks only a few keyframes, chosen where the shapes change most (greedy: the
frame worst predicted by linear interpolation between the keyframes already chosen, until every
frame is within a pixel or the budget is spent — what a person scrubbing the video does): lip
contours, eyelid contours and iris outlines in two or three views with ~1 px click noise, by the
same code that makes the capture's hand inputs (:func:`mifacerf.synthetic.hand_inputs.write_hand_inputs`).
Nothing of the in-between frames is marked.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..formats.files import write_json_atomic
from ..formats.performance import PerformanceWriter
from ..geometry.footprint import centre_footprint
from .performance import Script, script as make_script

TRUTH_FORMAT = "mifacerf.performance_truth"
LIP_CURVES = ("lip_upper", "lip_lower")
LID_CURVES = ("lid_upper_L", "lid_lower_L", "lid_upper_R", "lid_lower_R")
IRIS_CURVES = ("iris_L", "iris_R")


def studio_lights(n: int = 10, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Directions (L, 3) and RGB irradiance (L, 3) of the diffuse studio lighting.

    ``n`` lights on a Fibonacci spiral over the sphere, keeping those in front of the face
    (z > −0.25) — key, fill, top and bounce from below — with irradiance ``π / n_sphere`` each,
    i.e. the front part of a uniform environment of unit radiance, slightly warm.
    """
    m = int(round(n / 0.625))  # the cap z > -0.25 holds 62.5 % of the sphere
    i = np.arange(m) + 0.5
    y = 1 - 2 * i / m
    r = np.sqrt(1 - y * y)
    ph = np.pi * (1 + 5 ** 0.5) * i + seed
    d = np.stack([r * np.sin(ph), y, r * np.cos(ph)], 1)
    d = d[d[:, 2] > -0.25]
    irr = np.tile(np.array([1.0, 0.97, 0.92]) * (4 * np.pi / m), (len(d), 1))
    return d, irr


_RAYS: dict = {}


def _camera_rays(camera: Camera, spp: int, seed: int):
    """The camera's primary rays, cached: a video camera samples the same sub-pixel pattern every frame."""
    from .olat import camera_rays

    key = (camera.name, camera.width, camera.height, tuple(np.round(camera.K.ravel(), 9)),
           tuple(np.round(camera.R.ravel(), 12)), tuple(np.round(camera.t, 12)), spp, seed)
    if key not in _RAYS:
        if len(_RAYS) > 32:
            _RAYS.clear()
        _RAYS[key] = camera_rays(camera, spp, seed)
    return _RAYS[key]


def render_lit(scene, camera: Camera, directions: np.ndarray, irradiance: np.ndarray, spp: int = 4,
               seed: int = 0) -> np.ndarray:
    """(H, W, 3) linear RGB of ``scene`` lit by directional lights, ray-traced shadows, box filter.

    The same light transport as :func:`mifacerf.synthetic.olat.render_olat` summed over the lights,
    but one lane per camera sample (no compaction to the hits), so the kernel's shape never
    changes and Dr.Jit compiles it once for the whole video.
    """
    import drjit as dr

    from ..jitarrays import from_jit, to_jit
    from ..variant import ensure_variant

    mi = ensure_variant()
    ray = _camera_rays(camera, spp, seed)
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    bsdf = si.bsdf()
    ctx = mi.BSDFContext()
    D = to_jit(mi.Vector3f, np.asarray(directions, np.float32).T)
    E = to_jit(mi.Color3f, np.asarray(irradiance, np.float32).T)
    n = dr.opaque(mi.UInt32, len(directions))

    def body(i, acc):
        wi = dr.gather(mi.Vector3f, D, i)
        e = dr.gather(mi.Color3f, E, i)
        value = bsdf.eval(ctx, si, si.to_local(wi), valid)
        nonzero = valid & ((value.x > 0) | (value.y > 0) | (value.z > 0))
        lit = nonzero & ~scene.ray_test(si.spawn_ray(wi), nonzero)
        return i + 1, acc + dr.select(lit, value * e, 0.0)

    _, acc = dr.while_loop((dr.opaque(mi.UInt32, 0, 1), dr.zeros(mi.Color3f, dr.width(valid))),
                           lambda i, acc: i < n, body)
    dr.eval(acc)
    img = from_jit(acc).reshape(camera.height, camera.width, spp, 3).mean(2)
    if not np.isfinite(img).all():
        raise FloatingPointError("the performance render produced NaN/Inf pixels")
    return img.astype(np.float32)


def sensor_noise(image: np.ndarray, seed: int, read: float = 0.002, shot: float = 0.004) -> np.ndarray:
    """A video camera's noise: Gaussian read noise plus signal-dependent shot noise (σ² = read² + shot²·x),
    clipped at 0. Also what tells two real exposures apart (a bit-identical frame is a duplicate)."""
    rng = np.random.default_rng(seed)
    x = np.maximum(np.asarray(image, np.float32), 0.0)
    sigma = np.sqrt(read * read + shot * shot * x)
    return np.maximum(x + sigma * rng.standard_normal(x.shape).astype(np.float32), 0.0)


def render_frame(scene, camera: Camera, lighting: dict, spp: int, seed: int) -> np.ndarray:
    """(H, W, 3) linear RGB of the posed subject under the performance lighting."""
    if lighting["type"] == "studio":
        return render_lit(scene, camera, np.asarray(lighting["directions"]), np.asarray(lighting["irradiance"]),
                          spp=spp, seed=seed)
    from .truth import render_truth

    return render_truth(scene, camera, spp=spp, seed=seed)[..., :3]


def lighting_spec(kind: str = "studio") -> dict:
    if kind == "studio":
        d, irr = studio_lights()
        return {"type": "studio", "directions": np.round(d, 6).tolist(), "irradiance": np.round(irr, 6).tolist(),
                "description": "directional lights with ray-traced shadows spread over the front of the face"}
    if kind == "constant":
        return {"type": "constant", "radiance": [1.0, 1.0, 1.0],
                "description": "uniform white environment, Mitsuba path tracer (noisy at low spp)"}
    raise ValueError(f"unknown performance lighting {kind!r}; use 'studio' or 'constant'")


# --------------------------------------------------------------------------------- keyframes
def greedy_keyframes(signal: np.ndarray, tol: float, budget: int, must: list[int] | None = None,
                     first: int = 0) -> list[int]:
    """Frames to mark so that linear interpolation between them predicts ``signal`` (N, K) within ``tol``.

    Starts from ``first``, the last frame and ``must``; adds the worst-predicted frame until the
    largest error (Euclidean norm per frame, max over K/3 points) is below ``tol`` or ``budget``
    keyframes are chosen.
    """
    n = len(signal)
    X = np.asarray(signal, np.float64).reshape(n, -1, 3) if signal.ndim == 2 and signal.shape[1] % 3 == 0 \
        else np.asarray(signal, np.float64).reshape(n, -1, 1)
    keys = sorted(set([first, n - 1] + list(must or [])))
    while len(keys) < budget:
        pred = interpolate_keys(X, keys)
        err = np.linalg.norm(pred - X, axis=-1).max(axis=1)
        err[keys] = 0
        worst = int(np.argmax(err))
        if err[worst] <= tol:
            break
        keys = sorted(keys + [worst])
    return keys


def interpolate_keys(X: np.ndarray, keys: list[int]) -> np.ndarray:
    """Piecewise-linear interpolation of X (N, ...) through the frames ``keys``."""
    n = len(X)
    keys = np.asarray(sorted(keys))
    f = np.arange(n)
    k1 = np.clip(np.searchsorted(keys, f, side="left"), 1, len(keys) - 1)
    a, b = keys[k1 - 1], keys[k1]
    w = np.clip((f - a) / np.maximum(b - a, 1), 0, 1).reshape((-1,) + (1,) * (X.ndim - 1))
    return (1 - w) * X[a] + w * X[b]


def choose_keyframes(truth: dict, template, fps: float, footprint: float, lead_in_frames: int) -> dict:
    """The synthetic user's keyframes {"lips", "eyelids", "irises": [frames]} (see the module docstring)."""
    from ..geometry.margins import margins_from_holes

    V = truth["template_vertices"]
    head = truth["head"]
    n = len(V)
    # express in the head frame: the user judges shape changes, not the head's motion
    Vh = np.einsum("nij,ntj->nti", np.transpose(head[:, :3, :3], (0, 2, 1)), V - head[:, None, :3, 3])
    margins = margins_from_holes(template.get("holes") or {}, [v["kind"] for v in template["vertices"]])
    lip_ids = np.unique(np.concatenate([margins[k] for k in LIP_CURVES if k in margins]))
    lid_ids = np.unique(np.concatenate([margins[k] for k in LID_CURVES if k in margins]))
    seconds = n / fps
    start = min(lead_in_frames, n - 1)
    out = {"lips": greedy_keyframes(Vh[:, lip_ids].reshape(n, -1), 1.0 * footprint,
                                    max(3, int(np.ceil(5 * seconds))), [start], 0),
           "eyelids": greedy_keyframes(Vh[:, lid_ids].reshape(n, -1), 1.0 * footprint,
                                       max(3, int(np.ceil(5 * seconds))), [start], 0)}
    # gaze of both eyes in the head frame (unit vectors, compared in units of ~iris-mark precision)
    g = np.einsum("nij,nkj->nki", np.transpose(head[:, :3, :3], (0, 2, 1)), truth["eyes"][:, :, :3, 2])
    out["irises"] = greedy_keyframes(g.reshape(n, -1) * 0.012, 0.5 * footprint,
                                     max(3, int(np.ceil(4 * seconds))), [start], 0)
    return out


def keyframe_marks(subject, params: np.ndarray, keys: dict, cameras: list[Camera], seed: int = 0) -> dict:
    """Rotoscope dicts {frame: mifacerf.rotoscope} made by the synthetic user at the keyframes only."""
    from ..rig import LightStage, Rig
    from .hand_inputs import write_hand_inputs
    from .presets import Expression

    wanted: dict[int, set] = {}
    for kind, curves in (("lips", LIP_CURVES), ("eyelids", LID_CURVES), ("irises", IRIS_CURVES)):
        for f in keys.get(kind, []):
            wanted.setdefault(int(f), set()).update(curves)
    if not wanted:
        return {}
    frames = sorted(wanted)
    exprs = [Expression(f"F{f:05d}", "neutral" if i == 0 else "other", params[f]) for i, f in enumerate(frames)]
    poses = {e.name: subject.pose(e.params, textures=False) for e in exprs}
    rig = Rig(LightStage([[0.0, 1.0, 0.0]], [4 * np.pi], [[1.0, 1.0, 1.0]], [-1], [-1]), cameras)
    tmp = Path(tempfile.mkdtemp(prefix="perf-hand-"))
    try:
        write_hand_inputs(tmp, subject, exprs, poses, rig, seed=seed + 17)
        out = {}
        for f in frames:
            d = json.loads((tmp / "hand" / "rotoscope" / f"F{f:05d}.json").read_text())
            d["curves"] = {k: v for k, v in d.get("curves", {}).items() if k in wanted[f]}
            d["points"] = {}
            d["eyes_look_at"] = None
            d["frame"] = f
            d["marked"] = sorted(wanted[f])
            out[f] = d
        return out
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# --------------------------------------------------------------------------------- recording
def performance_truth(subject, sc: Script) -> dict:
    """Per-frame truth arrays of a scripted performance (no rendering)."""
    T, D, heads, eyes, jaws = [], [], [], [], []
    for p in sc.params:
        pose = subject.pose(p, textures=False)
        T.append(pose.template_vertices)
        D.append(pose.dots)
        heads.append(pose.transforms["head"])
        eyes.append([pose.transforms["eye_left"], pose.transforms["eye_right"]])
        jaws.append(pose.transforms["jaw"])
    return {"params": sc.params, "template_vertices": np.asarray(T), "dots": np.asarray(D),
            "head": np.asarray(heads), "eyes": np.asarray(eyes), "jaw": np.asarray(jaws)}


def write_truth(truth_dir: Path, sc: Script, truth: dict, keys: dict, extra: dict) -> None:
    truth_dir.mkdir(parents=True, exist_ok=True)
    tmp = truth_dir / ".frames.tmp.npz"
    np.savez_compressed(tmp, **truth)
    os.replace(tmp, truth_dir / "frames.npz")
    write_json_atomic(truth_dir / "performance.json", {
        "format": TRUTH_FORMAT, "version": 1, "fps": sc.fps, "n_frames": sc.n_frames,
        "controls": sc.control_names, "events": sc.events, "keyframes": keys, **extra})


def read_truth(out_or_dir) -> dict:
    """The truth of a recorded performance: {'meta': performance.json, + the arrays of frames.npz}."""
    p = Path(out_or_dir)
    for cand in (p, p / "truth" / "performance", p / "performance"):
        if (cand / "frames.npz").exists() and (cand / "performance.json").exists():
            d = dict(np.load(cand / "frames.npz"))
            d["meta"] = json.loads((cand / "performance.json").read_text())
            return d
    raise FileNotFoundError(f"{p}: no performance truth (truth/performance/frames.npz) here")


def record_performance(out, seconds: float = 2.0, fps: float = 60.0, size: int | None = 192, spp: int = 4,
                       seed: int = 0, lighting: str = "studio", cameras: list[Camera] | None = None,
                       template: dict | None = None, subject=None, progress: bool = True,
                       keyframes: bool = True, log=None) -> Path:
    """Record the synthetic performance into ``OUT/performance`` (truth: ``OUT/truth/performance``).

    ``cameras`` / ``template`` default to the capture's (``OUT/capture``: its rig's cameras and the
    user's ``hand/template.json``); ``size`` the video resolution (square; None keeps the
    cameras'). Resumable: frames already on disk in every camera are not rendered again.
    """
    from tqdm.auto import tqdm

    from . import SubjectScene
    from .synth import load_subject, subject_from_truth

    out = Path(out)
    cap = out / "capture"
    if cameras is None or template is None:
        if not (cap / "manifest.json").exists():
            raise FileNotFoundError(f"{cap}: no capture here; record the light-stage capture first "
                                    "(mifacerf synth OUT) or pass cameras and a template")
        from ..formats.capture import Capture

        capture = Capture(cap)
        cameras = cameras or list(capture.rig.cameras)
        if template is None:
            tp = cap / "hand" / "template.json"
            if not tp.exists():
                raise FileNotFoundError(f"{tp}: missing (the user's template)")
            template = json.loads(tp.read_text())
    if subject is None:
        subject = subject_from_truth(out) if (out / "truth" / "truth.json").exists() else load_subject(None)
    cams = [c.resized(size, size) if size else c for c in cameras]
    sc = make_script(seconds, fps, seed, controls=subject.controls)
    n = sc.n_frames
    light = lighting_spec(lighting)
    perf = out / "performance"
    writer = PerformanceWriter(perf, cams, fps, n, template, extra={
        "lighting": light, "starts_at_rest": True, "spp": spp,
        "subject": {"name": getattr(subject, "name", "synthetic"), "synthetic": True},
        "dot_radius": float(getattr(subject, "dot_radius", template.get("dot_radius", 0.0015)))})
    scene = SubjectScene(subject, extra=None if light["type"] == "studio" else
                         {"env": {"type": "constant", "radiance": {"type": "rgb", "value": light["radiance"]}}})
    bar = tqdm(total=n * len(cams), desc="performance", unit="img", disable=not progress)
    t0 = time.perf_counter()
    with ThreadPoolExecutor(max_workers=1) as pool:
        pending = []
        for f in range(n):
            if writer.has_frame(f):
                bar.update(len(cams))
                continue
            scene.set_pose(subject.pose(sc.params[f]))
            for c, cam in enumerate(cams):
                img = sensor_noise(render_frame(scene.scene, cam, light, spp, seed),
                                   seed * 7_000_003 + f * 101 + c)
                pending.append(pool.submit(writer.write, cam.name, f, img))
                bar.update(1)
            done = [p for p in pending if p.done()]
            for p in done:
                p.result()
            pending = [p for p in pending if not p.done()]
        for p in pending:
            p.result()
    bar.close()
    render_s = time.perf_counter() - t0
    truth = performance_truth(subject, sc)
    fp = centre_footprint(cams)
    lead = int(np.ceil(0.2 * fps))
    keys = choose_keyframes(truth, template, fps, fp, lead) if keyframes else {"lips": [], "eyelids": [], "irises": []}
    marks = keyframe_marks(subject, sc.params, keys, cams, seed) if keyframes else {}
    writer.write_keyframes(keys, marks)
    write_truth(out / "truth" / "performance", sc, truth, keys,
                {"cameras": [c.name for c in cams], "render_seconds": round(render_s, 2), "size": size,
                 "spp": spp, "lighting": light["type"], "seed": seed})
    if log:
        log(f"performance: {n} frames x {len(cams)} cameras in {render_s:.1f} s; keyframes "
            + ", ".join(f"{k} {len(v)}" for k, v in keys.items()))
    return writer.finish()
