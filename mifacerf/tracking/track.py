"""``mifacerf track PERF``: from a multi-view performance to a per-frame target mesh.

Reads only the performance folder (frames, cameras, the user's template and keyframe marks,
:mod:`.folder`) and, optionally, a model (its registered neutral is a better rest reference than
the user's clicked template, and it knows where the eyeballs are). Never reads ground truth.

Writes ``TRACK/`` (default ``PERF/track``)::

    track.json    format, inputs, options, per-frame camera problems, counts, keyframes used, timing
    track.npz     vertices (N, T, 3)   the target mesh per frame, template topology, world, metres
                  status (N, T) int8   1 from the data (tracked dot; vertex placed from tracked dots or
                                       keyframes), 0 predicted only (untracked: from neighbours / time);
                                       the template's extensions (scalp, ears, neck) placed as the
                                       registration places them: rigid with the frame's head pose or
                                       driven by the nearest tracked dots (registration.extensions)
                  dots (N, D, 3)       tracked dot positions (smoothed, gaps filled)
                  dot_status (N, D)    1 tracked, 0 untracked in that frame
                  dot_ids (D,)         template ids of the dots
                  uv (N, C, D, 2)      every dot's image position used in every camera (NaN: not used)
                  reprojection (N, D)  RMS reprojection error (pixels) of tracked dots
                  redetected (N, D)    a lost dot found again in that frame
                  camera_status (N, C) 0 ok, 1 missing (dropped), 2 duplicate, 3 dark
                  head_pose (N, 4, 4)  neutral → frame
                  eyes (N, 2, 4, 4)    eyeball rest → world (left, right); gaze (N, 2, 3) world unit vectors
                  frame_seconds (N,)   tracking time per frame

The folder is one transaction (:class:`mifacerf.formats.files.OutputFolder`): written beside ``TRACK``
and swapped in complete (with whatever another command wrote inside the old one, e.g. ``TRACK/drive``,
hard-linked over), so a failed, killed or out-of-space tracking leaves the previous track as it was; a
second ``track`` on the same folder is refused while one runs (exit 3), and a folder that holds files but
no ``track.json`` is never replaced. :class:`Track` finishes an interrupted swap when it opens one.
"""
from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

from ..formats.files import OutputFolder, repair_if_needed, write_json_atomic
from ..registration.contours import propagate, rings
from ..registration.extensions import extensions_from_template, place_in_expression
from ..registration.hand import Template, read_hand_inputs
from ..geometry.schaefer2006 import mls_affine
from ..stats import median_p95
from . import health as HL
from ..formats.performance import PerformanceFolder
from .keyframes import LID_MARGINS, LIP_MARGINS, eye_tracks, margin_tracks
from .track3d import DotTracker, Options, finish_dots, head_poses, rigid_dot_set
from ..errors import MifacerfError

FORMAT = "mifacerf.track"
VERSION = 1
OWN = ("track.json", "track.npz")     #: what tracking writes (and overlay_F*.png): a new track replaces them


class TrackError(MifacerfError, ValueError):
    """Tracking cannot start (the message says which input is missing or unusable)."""


def reference(template: Template, model=None) -> tuple[np.ndarray, dict, str]:
    """Rest positions (T, 3), eyeball centres in the head frame {"L", "R"} and where they come from."""
    eyes = {s: np.asarray(e["centre"], np.float64) for s, e in template.eyes.items() if "centre" in e}
    if model is None:
        return template.vertices.copy(), eyes, "template (the user's clicks on the neutral)"
    if model.n_vertices != template.n_vertices:
        raise TrackError(f"the model has {model.n_vertices} template vertices, the performance's template "
                         f"{template.n_vertices}: they are not the same template")
    s = model.expression_index(model.neutral)
    H = np.asarray(model.head_pose[s], np.float64)
    Hinv = np.linalg.inv(H)
    V = model.vertices[s] @ Hinv[:3, :3].T + Hinv[:3, 3]
    ec = np.asarray(model.eye_centres[s], np.float64)
    for i, side in enumerate(("L", "R")):
        if np.isfinite(ec[i]).all():
            eyes[side] = Hinv[:3, :3] @ ec[i] + Hinv[:3, 3]
    return V, eyes, f"model {model.root} (registered {model.neutral})"


def place_extensions_per_frame(tpl: Template, V_ref, V, status, head) -> dict:
    """Place ``tpl``'s extensions in every tracked frame (``V`` (N, T, 3) and ``status`` (N, T) updated in
    place) with :func:`mifacerf.registration.extensions.place_in_expression`: from the rest positions
    ``V_ref`` (T, 3), the frame's tracked dots (status 1) and its head pose ``head`` (N, 4, 4, rest →
    frame). A frame without a finite head pose keeps the dots' map. Returns {"frames": placed, "fallbacks":
    the messages of the first frame that had any}."""
    exts = extensions_from_template(tpl.raw, tpl.n_vertices)
    report = {"frames": 0, "fallbacks": []}
    if not exts:
        return report
    for f in range(len(V)):
        if not np.isfinite(head[f]).all():
            continue
        rep = place_in_expression(V_ref, tpl.triangles, tpl.dot_ids, exts, V[f], status[f], head[f])
        report["frames"] += 1
        if rep["fallbacks"] and not report["fallbacks"]:
            report["fallbacks"] = [f"frame {f}: {m}" for m in rep["fallbacks"]]
    return report


def _load_model(model):
    if model is None or not isinstance(model, (str, os.PathLike)):
        return model
    from ..rendering.model import Model

    return Model(model)


def track_performance(perf, out=None, model=None, options: Options | None = None, frames=None,
                      progress: bool = True, log=None) -> Path:
    """Track ``perf`` (a path or :class:`PerformanceFolder`); returns the track folder."""
    perf = perf if isinstance(perf, PerformanceFolder) else PerformanceFolder(perf)
    target = Path(out) if out is not None else perf.root / "track"
    # one transaction, locked from the start (a second track on it: exit 3); what another command wrote
    # inside (TRACK/drive) is kept
    with OutputFolder(target, "track.json", TrackError, what="track",
                      carry=lambda name: name not in OWN and not name.startswith("overlay_F")) as output:
        meta = _track(perf, output.root, output.target, model, options, frames, progress)
        output.finish()
    if log:
        log(f"tracked {meta['n_frames']} frames: {100 * meta['dots_tracked_per_frame']['mean']:.1f}% of dot-frames, "
            f"{100 * meta['dots_tracked_whole_sequence']:.1f}% of dots throughout; "
            f"{len(meta['camera_problems'])} camera problem(s)")
    return target


def _track(perf: PerformanceFolder, out: Path, target: Path, model, options, frames, progress) -> dict:
    """:func:`track_performance`'s work, written into ``out`` (the new folder of ``target``); returns the
    track.json it wrote."""
    from tqdm.auto import tqdm

    opt = options or Options()
    model = _load_model(model)
    hand = read_hand_inputs(perf.root, perf.camera_names)
    if hand.template is None:
        raise TrackError(f"{perf.template_path}: no usable template ({'; '.join(hand.problems)})")
    tpl = hand.template
    V_ref, eye_centres, ref_src = reference(tpl, model)
    n = perf.n_frames if frames is None else min(int(frames), perf.n_frames)
    cams = perf.cameras
    names = perf.camera_names
    tracker = DotTracker(cams, V_ref, tpl.triangles, tpl.dot_ids, tpl.dot_radius, n, opt)
    healths = [HL.CameraHealth(opt.dark_ratio) for _ in cams]
    cam_status = np.zeros((n, len(cams)), np.int8)
    frame_s = np.zeros(n)
    bar = tqdm(total=n, desc="track", unit="frame", disable=not progress)
    for f in range(n):
        t0 = time.perf_counter()
        images, levels = {}, {}
        for c, name in enumerate(names):
            img = perf.read(name, f)
            st = healths[c].check(img)
            cam_status[f, c] = st
            if st == HL.OK:
                images[name] = img
                levels[name] = float(np.mean(img))
        if len(levels) >= 3:   # a camera far darker than the others in the same frame is dark too
            med = float(np.median(list(levels.values())))
            for c, name in enumerate(names):
                if name in levels and levels[name] < opt.dark_ratio * med:
                    cam_status[f, c] = HL.DARK
                    images.pop(name)
        tracker.step(f, images)
        frame_s[f] = time.perf_counter() - t0
        bar.update(1)
        bar.set_postfix_str(f"tracked {int(tracker.status[f].sum())}/{tracker.status.shape[1]}")
    bar.close()
    if tracker.detector is None:
        raise TrackError("no frame with at least two usable cameras: nothing could be tracked")

    t0 = time.perf_counter()
    X = finish_dots(tracker)
    dst = tracker.status
    rigid = rigid_dot_set(tpl, V_ref)
    head = head_poses(X, dst, tracker.X_ref, rigid)
    # the template per frame: dots, the rest carried by the tracked dots (as registration places extras)
    T = tpl.n_vertices
    dots = tpl.dot_ids
    extras = np.flatnonzero(~tpl.is_dot)
    V = np.empty((n, T, 3))
    status = np.zeros((n, T), np.int8)
    for f in range(n):
        V[f, dots] = X[f]
        status[f, dots] = dst[f]
        anchors = dst[f] == 1
        if anchors.sum() < 4:
            anchors = np.ones(len(dots), bool)
        V[f, extras] = mls_affine(tracker.X_ref[anchors], X[f, anchors], V_ref[extras], k=16)
        status[f, extras] = 1 if (dst[f] == 1).sum() >= 4 else 0
    # the template's extensions (scalp, ears, neck) as the registration places them: rigid with the head
    # pose, or driven by the nearest tracked dots with a falloff (registration.extensions)
    ext_report = place_extensions_per_frame(tpl, V_ref, V, status, head)
    # lips and eyelids from the keyframes, then the band round them follows (as registration does)
    keys = perf.keyframes()
    keyed = {m: keys["lips"] for m in LIP_MARGINS}
    keyed.update({m: keys["eyelids"] for m in LID_MARGINS})
    margins = {k: v for k, v in tpl.margins.items() if k in keyed}
    camd = {c.name: c for c in cams}
    rotoscope = rotoscope_by_frame(hand.rotoscope)
    M, margin_report = margin_tracks(V, X, margins, keyed, rotoscope, camd, tracker.X_ref, V_ref)
    if margins:
        margin_ids = np.unique(np.concatenate([np.asarray(v) for v in margins.values()]))
        dist = rings(T, tpl.triangles, margin_ids, 2)
        movable = np.flatnonzero((dist >= 0) & ~tpl.is_dot)
        for f in range(n):
            V0 = V[f].copy()
            for name, ids in margins.items():
                V[f, ids] = M[name][f]
            V[f] = propagate(V0, V[f], tpl.triangles, margin_ids, movable)
    keyed_any = {m for m, r in margin_report.items() if r["keyframes"]}
    for name in set(margins) - keyed_any:
        status[:, margins[name]] = 0
    eyes, gaze, eye_report = eye_tracks(head, eye_centres, keys["irises"], rotoscope, cams)
    finish_s = time.perf_counter() - t0

    tmp = out / ".track.tmp.npz"
    np.savez_compressed(tmp, vertices=V, status=status, dots=X, dot_status=dst, dot_ids=dots,
                        uv=tracker.uv, reprojection=tracker.reproj, redetected=tracker.redetected,
                        camera_status=cam_status, head_pose=head, eyes=eyes, gaze=gaze, frame_seconds=frame_s)
    os.replace(tmp, out / "track.npz")
    D = len(dots)
    usable = (cam_status == HL.OK).sum(1) >= 2
    whole = dst[usable].all(0) if usable.any() else np.zeros(D, bool)
    problems = []
    for c, name in enumerate(names):
        for code in (HL.MISSING, HL.DUPLICATE, HL.DARK):
            fr = np.flatnonzero(cam_status[:, c] == code)
            if len(fr):
                problems.append(f"camera {name}: {len(fr)} {HL.NAMES[code]} frame(s) {_ranges(fr)}")
    lost = [int(d) for d in np.flatnonzero(~whole)]
    meta = {
        "format": FORMAT, "version": VERSION,
        "performance": os.path.relpath(perf.root.resolve(), target.resolve()),
        "reference": ref_src, "model": None if model is None else str(Path(model.root).resolve()),
        "n_frames": n, "fps": perf.fps, "cameras": names, "n_dots": D,
        "options": opt.to_dict(), "detector": tracker.detector.to_dict(), "init_frame": tracker.init_frame,
        "frames_usable": int(usable.sum()),
        "dots_tracked_per_frame": {"mean": round(float(dst.mean()), 4), "min": int(dst.sum(1).min())},
        "dots_tracked_whole_sequence": round(float(whole.mean()), 4),
        "dots_not_tracked_throughout": lost[:50] + (["..."] if len(lost) > 50 else []),
        "redetections": int(tracker.redetected.sum()),
        "reprojection_px": median_p95(tracker.reproj[dst == 1]),
        "camera_problems": problems,
        "frames_without_two_usable_cameras": _ranges(np.flatnonzero(~usable)),
        "lips_eyelids": margin_report, "eyes": eye_report, "keyframes": keys,
        "head_pose": f"robust rigid fit of {len(rigid)} forehead / nose / ear dots per frame",
        "extensions": ext_report,
        "time_s": {"per_frame_mean": round(float(frame_s.mean()), 4), "frames_total": round(float(frame_s.sum()), 2),
                   "finish": round(finish_s, 2)},
        "hand_input_problems": [p for p in hand.problems if "coarse_points" not in p],
    }
    write_json_atomic(out / "track.json", meta)
    return meta


def rotoscope_by_frame(rotoscope: dict) -> dict:
    """The performance's rotoscope entries {frame: Rotoscope} (files ``hand/rotoscope/F<frame:05d>.json``)."""
    out = {}
    for name, rot in rotoscope.items():
        if len(name) > 1 and name[0] == "F" and name[1:].isdigit():
            out[int(name[1:])] = rot
    return out


def _ranges(frames) -> str:
    frames = [int(f) for f in frames]
    if not frames:
        return ""
    out, start, prev = [], frames[0], frames[0]
    for f in frames[1:] + [None]:
        if f is not None and f == prev + 1:
            prev = f
            continue
        out.append(f"{start}" if start == prev else f"{start}-{prev}")
        if f is not None:
            start = prev = f
    return ",".join(out)


class Track:
    """A track folder opened for reading."""

    def __init__(self, root):
        self.root = Path(root)
        repair_if_needed(self.root, "track.json", TrackError)
        p = self.root / "track.json"
        if not p.exists():
            raise TrackError(f"{p}: missing; run 'mifacerf track PERF' first")
        self.meta = json.loads(p.read_text())
        if self.meta.get("format") != FORMAT:
            raise TrackError(f"{p}: not a {FORMAT} file")
        z = np.load(self.root / "track.npz")
        self.arrays = {k: z[k] for k in z.files}

    def __getattr__(self, name):
        try:
            return self.__dict__["arrays"][name]
        except KeyError:
            raise AttributeError(name) from None

    @property
    def n_frames(self) -> int:
        return int(self.meta["n_frames"])

    @property
    def fps(self) -> float:
        return float(self.meta["fps"])

    @property
    def performance(self) -> Path:
        return (self.root / self.meta["performance"]).resolve()
