"""``mifacerf synth``: photograph a synthetic subject through the simulated light stage.

Writes ``OUT/capture/`` — a capture folder exactly as a real rig would (docs/capture-format.md),
including the hand-made registration inputs a user would supply — and ``OUT/truth/``,
the ground truth that only evaluation may read::

    OUT/truth/truth.json                 subject, controls, preset, expressions with their parameter vectors
    OUT/truth/expressions/<name>.npz     params, skin_vertices (V, 3), dots (D, 3), template_vertices (T, 3),
                                         part transforms (rigid parts, 4x4 each)

Images are rendered by :func:`mifacerf.synthetic.olat.render_olat` (one Dr.Jit
wavefront per batch of lights) and written while the next camera renders. An
interrupted run resumes: (expression, camera) pairs whose images are all present are
skipped (every image is written atomically, so a present file is a whole file); the
manifest is written last.
"""
from __future__ import annotations

import json
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..formats.capture import IMAGE_PATTERN, CaptureError, CaptureWriter, ExpressionEntry
from ..formats.files import sha256_file, write_json_atomic
from ..rig import Rig, RigPreset, preset as get_preset
from .olat import render_olat

TRUTH_FORMAT = "mifacerf.truth"


def load_subject(subject_folder: str | os.PathLike | None = None, options: dict | None = None, cameras=None):
    """The default procedural subject, or a user's blendshape subject from a folder (``options``:
    :func:`~.mesh_subject.load_mesh_subject` keywords such as ``scale``, ``n_dots``, ``shapes``;
    ``cameras``: the capture cameras, which decide where the dots go)."""
    from . import default_subject, load_mesh_subject

    if subject_folder is None:
        return default_subject()
    return load_mesh_subject(subject_folder, cameras=cameras, **(options or {}))


def subject_folder_of(out: str | os.PathLike, truth: dict) -> Path | None:
    """The subject folder a synth output was made from (None: the embedded head). ``truth.json``
    records it relative to the output folder (and absolute, as it was then); a folder found at
    neither place is an error naming both."""
    entry = truth.get("subject", {})
    rel, absolute = entry.get("folder_relative"), entry.get("folder")
    if rel is None and absolute is None:
        return None
    out = Path(out)
    cands = ([out / rel] if rel is not None else []) + ([Path(absolute)] if absolute is not None else [])
    for c in cands:
        if c.is_dir():
            return c
    where = " nor ".join(str(c) for c in cands)
    raise FileNotFoundError(f"{out / 'truth' / 'truth.json'}: the subject folder is gone: neither {where} exists; "
                            "move the folder back (or edit \"folder_relative\" in truth.json)")


def subject_from_truth(out: str | os.PathLike, cameras=None):
    """The subject of a synth output folder (or of its truth/ folder), loaded as ``mifacerf synth``
    loaded it: the folder found by :func:`subject_folder_of`, the options recorded, the capture's cameras."""
    out = Path(out)
    if (out / "truth.json").exists() and not (out / "truth").is_dir():
        out = out.parent
    truth = read_truth(out)
    folder = subject_folder_of(out, truth)
    if cameras is None and folder is not None and (out / "capture").is_dir():
        from ..formats.capture import Capture

        cameras = Capture(out / "capture").rig.cameras
    return load_subject(folder, truth.get("subject", {}).get("options"), cameras)


def choose_expressions(subject, preset: RigPreset, names: list[str] | None = None):
    """The preset's expressions (or the named ones, in that order)."""
    exprs = subject.presets(preset.name)
    if names:
        by_name = {e.name: e for e in subject.presets("paper")}
        unknown = [n for n in names if n not in by_name]
        if unknown:
            raise ValueError(f"unknown expression(s) {', '.join(unknown)}; known: {', '.join(by_name)}")
        exprs = [by_name[n] for n in names]
    return exprs


def write_truth_expression(truth_dir: Path, name: str, params: np.ndarray, pose) -> None:
    path = truth_dir / "expressions" / f"{name}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    parts = {f"part_{k}": np.asarray(p.transform) for k, p in pose.parts.items()
             if getattr(p, "transform", None) is not None}
    tmp = path.with_name(f".{name}.tmp.npz")
    np.savez_compressed(tmp, params=np.asarray(params), skin_vertices=np.asarray(pose.skin_vertices, np.float32),
                        dots=np.asarray(pose.dots), template_vertices=np.asarray(pose.template_vertices), **parts)
    os.replace(tmp, path)


def synthesize(out: str | os.PathLike, preset: str = "draft", subject_folder=None, expressions=None,
               overwrite: bool = False, progress: bool = True, rig: Rig | None = None, seed: int = 0,
               executor=None, subject_options: dict | None = None, report=None) -> Path:
    """Render the capture of a synthetic subject into ``out``; returns the capture folder.

    ``subject_options``: keywords for a user's subject (:func:`~.mesh_subject.load_mesh_subject`:
    ``scale``, ``n_dots``, ``shapes``, ``placement``), recorded in ``truth.json``; ``report``: called with
    each line the subject's loader reports (what was read, repaired, placed, the template's coverage).

    ``executor`` (:mod:`mifacerf.execution`): on a cluster each (expression, camera) take is one unit
    (:func:`synth_take`: a worker renders its images and writes them into the shared capture folder through
    the same writer); without one, or with one process, this process renders them as before."""
    from tqdm.auto import tqdm

    from . import SubjectScene
    from .hand_inputs import write_hand_inputs

    pre = get_preset(preset)
    out = Path(out)
    cap_dir, truth_dir = out / "capture", out / "truth"
    if (cap_dir / "manifest.json").exists() and not overwrite:
        raise CaptureError(f"{cap_dir}: already holds a complete capture; use --overwrite or another folder")
    rig = rig or pre.rig()
    subject_options = {k: v for k, v in (subject_options or {}).items() if v is not None}
    subject = load_subject(subject_folder, subject_options, rig.cameras)
    for line in getattr(subject, "report", []) if report is not None else []:
        report(line)
    exprs = choose_expressions(subject, pre, expressions)
    writer = CaptureWriter(cap_dir, rig, [ExpressionEntry(e.name, e.category) for e in exprs],
                           extra={"subject": {"name": getattr(subject, "name", "synthetic"), "synthetic": True},
                                  "preset": pre.name}, overwrite=overwrite)
    truth_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(truth_dir / "truth.json", {
        "format": TRUTH_FORMAT, "version": 1, "preset": pre.name,
        "subject": {"name": getattr(subject, "name", "synthetic"),
                    "folder": None if subject_folder is None else str(Path(subject_folder).resolve()),
                    "folder_relative": None if subject_folder is None else
                    os.path.relpath(Path(subject_folder).resolve(), out.resolve()),
                    "options": subject_options},
        "controls": [c.name for c in subject.controls],
        "expressions": [{"name": e.name, "category": e.category, "params": np.asarray(e.params).tolist()}
                        for e in exprs],
        "dot_radius": float(getattr(subject, "dot_radius", 0.0)),
    })
    lights = rig.lights
    total = len(exprs) * len(rig.cameras) * len(lights)
    bar = tqdm(total=total, desc="synth", unit="img", disable=not progress, smoothing=0.05)
    poses = {}
    if executor is not None and executor.distributed:
        takes = []
        for e in exprs:
            pose = poses[e.name] = subject.pose(e.params)
            write_truth_expression(truth_dir, e.name, e.params, pose)
            for cam in rig.cameras:
                if _take_on_disk(writer, e.name, cam.name, len(lights)):  # resumed run: already written
                    bar.update(len(lights))
                else:
                    takes.append((e.name, np.asarray(e.params), cam.name))
        context = SynthContext(subject_folder, writer, pre.spp, seed)
        context.subject_options = subject_options
        for sums in executor.imap(synth_take, takes, context):
            writer.checksums.update(sums)
            bar.update(len(lights))
        _remove_stale_temporaries(writer.root, {(n, c) for n, _, c in takes})
    else:
        _synthesize_here(writer, subject, SubjectScene(subject), exprs, rig, truth_dir, poses, pre.spp, seed, bar)
    bar.close()
    write_hand_inputs(cap_dir, subject, exprs, poses, rig, seed=seed)
    writer.finish()
    return cap_dir


class SynthContext:
    """What every take unit shares: the subject (its folder, or None for the default), the capture writer
    (root, rig), spp and seed. A worker builds the subject's scene once (:func:`mifacerf.execution.worker_cached`)."""

    def __init__(self, subject_folder, writer: CaptureWriter, spp: int, seed: int):
        self.subject_folder = None if subject_folder is None else str(subject_folder)
        self.writer, self.spp, self.seed = writer, spp, seed


def synth_take(context: SynthContext, unit: tuple) -> dict:
    """One take ``(expression, params, camera)``: its images rendered and written (atomically) into the
    capture folder; returns their checksums {relative path: sha256}."""
    from ..execution import worker_cached
    from . import SubjectScene

    name, params, camera = unit
    options = getattr(context, "subject_options", None)
    subject, scene, posed = worker_cached(("synth subject", context.subject_folder, repr(options)), lambda: (
        lambda subj: (subj, SubjectScene(subj), {}))(load_subject(context.subject_folder, options,
                                                                  context.writer.rig.cameras)))
    if posed.get("name") != name:
        scene.set_pose(subject.pose(params))
        posed["name"] = name
    w, lights = context.writer, context.writer.rig.lights
    imgs = render_olat(scene.scene, w.rig.camera(camera), lights.directions, lights.irradiance, spp=context.spp,
                       seed=context.seed)
    sums = {}
    for l, img in enumerate(imgs):
        rel = w.write_image(name, camera, l, img).relative_to(w.root).as_posix()
        sums[rel] = w.checksums.pop(rel, None) or sha256_file(w.root / rel)
    return sums


def _synthesize_here(writer, subject, scene, exprs, rig, truth_dir, poses, spp, seed, bar) -> None:
    """The takes rendered in this process, each written by a thread while the next camera renders."""
    lights = rig.lights
    with ThreadPoolExecutor(max_workers=2) as pool:
        pending = []
        for e in exprs:
            pose = subject.pose(e.params)
            poses[e.name] = pose
            write_truth_expression(truth_dir, e.name, e.params, pose)
            posed = False
            for cam in rig.cameras:
                if _take_on_disk(writer, e.name, cam.name, len(lights)):  # resumed run: already written
                    bar.update(len(lights))
                    continue
                if not posed:
                    scene.set_pose(pose)
                    posed = True
                imgs = render_olat(scene.scene, cam, lights.directions, lights.irradiance, spp=spp,
                                   seed=seed)
                for f in pending:
                    f.result()
                pending = [pool.submit(_write_all, writer, e.name, cam.name, imgs, bar)]
        for f in pending:
            f.result()


def _remove_stale_temporaries(root: Path, takes) -> None:
    """Delete what a worker killed while writing left behind: the atomic writers' temporary files
    (``.<name>.<random>.tmp*``, :mod:`mifacerf.formats.files`) in the takes' image folders. Called once every
    take is complete, when no writer is left."""
    for expression, camera in takes:
        folder = (root / IMAGE_PATTERN.format(expression=expression, camera=camera, light=0)).parent
        for p in folder.glob(".*.tmp*"):
            p.unlink(missing_ok=True)


def _take_on_disk(writer: CaptureWriter, expression: str, camera: str, n_lights: int) -> bool:
    """Whether every image of the take is present (every image is written atomically, so a present file is a
    whole file); if so, their checksums are recorded in ``writer``."""
    paths = [writer.image_path(expression, camera, l) for l in range(n_lights)]
    if not all(p.exists() for p in paths):
        return False
    for p in paths:
        writer.checksums[p.relative_to(writer.root).as_posix()] = sha256_file(p)
    return True


def _write_all(writer: CaptureWriter, expression: str, camera: str, images: np.ndarray, bar) -> None:
    for l, img in enumerate(images):
        writer.write_image(expression, camera, l, img)
        bar.update(1)


def read_truth(out_or_truth: str | os.PathLike) -> dict:
    """``truth.json`` of a synth output folder (or of its truth/ folder)."""
    p = Path(out_or_truth)
    path = p / "truth.json" if (p / "truth.json").exists() else p / "truth" / "truth.json"
    if not path.exists():
        raise FileNotFoundError(f"{path}: no ground truth here (is this a 'mifacerf synth' output?)")
    return json.loads(path.read_text())
