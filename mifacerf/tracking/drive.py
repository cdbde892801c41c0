"""``mifacerf drive TRACK --model MODEL``: the model driven by a tracked performance (paper §6.4, §7).

Per frame of the track: the target mesh's §5 weights per vertex and region (the model's
:class:`~mifacerf.blending.BlendModel`, through :meth:`FaceModel.target`), filtered in time against
scintillation (:func:`smooth_weights`), rendered relit under each
environment from one camera with the rendering API, composited over the environment's plate
(:func:`mifacerf.rendering.api.composite`), written as an image sequence and an mp4 video.

``DRIVE/`` (default ``TRACK/drive``)::

    drive.json                       inputs, camera, per-frame timing, coherence (and what an observer
                                     adds: the truth comparison's PSNR, see below)
    weights.npz                      weights (N, T, S) float16, the §5 weights rendered (filtered in time);
                                     weights_unsmoothed, frames (N,), expressions (S,)
    <env>/frames/F<frame:05d>.png    the composite, sRGB 8-bit
    <env>/frames/F<frame:05d>.exr    the render itself, RGBA half float (premultiplied, linear)
    <env>/performance.mp4            the composite as a video at the performance's frame rate
    strip.png                        a strip of frames per environment (an observer's rows above)

The folder is one transaction (:class:`mifacerf.formats.files.OutputFolder`): written beside ``DRIVE``
and swapped in complete, so a failed, killed or out-of-space drive leaves the previous one as it was;
a second drive on the same folder is refused while one runs (exit 3), and a folder that holds files
but no ``drive.json`` is never replaced.

An ``observer`` (:class:`FrameObserver`) sees the weights and every rendered frame and adds entries
to ``drive.json`` and rows to the strip; driving itself never reads the synthetic truth. The
comparison with the path-traced truth (``mifacerf evaluate drive``) is such an observer,
:class:`mifacerf.evaluation.drive.TruthComparison`.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ..execution import Executor, worker_cached
from ..formats.files import OutputFolder, write_json_atomic
from .coherence import PixelCoherence, weight_summary
from .track import Track, TrackError

FORMAT = "mifacerf.drive"


def smooth_weights(W: np.ndarray, sigma: float) -> np.ndarray:
    """Per-vertex §5 weights (N, T, S) filtered in time (Gaussian, ``sigma`` frames; 0 = off), renormalised.

    Near a Delaunay cell boundary of a vertex's local deformation space, the tracked mesh's
    sub-millimetre noise flips the vertex between cells from frame to frame — the scintillation
    the paper's culling (§5.1) fights. A short temporal filter (2 frames = 33 ms at 60 fps) removes
    the flicker and keeps the changes that motion makes.
    """
    if sigma <= 0 or len(W) < 2:
        return W
    from scipy.ndimage import gaussian_filter1d

    Ws = np.clip(gaussian_filter1d(np.asarray(W, np.float64), sigma, axis=0, mode="nearest"), 0.0, None)
    return Ws / np.maximum(Ws.sum(-1, keepdims=True), 1e-12)


def frame_parts(face, track: Track, f: int, base: dict) -> dict:
    """Eye and teeth transforms of frame ``f``: the model's estimate from the mesh (jaw from the lower lip
    and chin), with the eyes from tracking (iris keyframes, relative to the head pose) and the
    head-rigid parts (upper teeth, mouth interior) on the tracked head pose."""
    parts = face.parts(mesh=track.vertices[f])
    for i, eye in enumerate(("eye_left", "eye_right")):
        if eye in base and np.isfinite(track.eyes[f, i]).all():
            parts[eye] = track.eyes[f, i] @ base[eye]
    for p in ("teeth_upper", "mouth_interior"):
        if p in base:
            parts[p] = track.head_pose[f] @ base[p]
    return parts


def exposure_for(images) -> float:
    """One exposure for a whole sequence: the 99th percentile of the first frame's covered pixels → 0.9."""
    img = np.asarray(images)
    vals = img[..., :3][img[..., 3] > 0.5] if img.shape[-1] == 4 else img.reshape(-1, 3)
    p = float(np.percentile(vals, 99)) if vals.size else 1.0
    return 0.9 / max(p, 1e-6)


class FrameContext:
    """What every frame unit of one environment shares: the model, the environment, the camera, spp.

    Pickled (sent to a worker) it keeps the model's folder instead of the loaded model; a worker loads
    it once (:func:`mifacerf.execution.worker_cached`), with the same field cache size, for all its frames."""

    def __init__(self, face, env, camera, spp: int):
        self._face, self.root, self.env, self.camera, self.spp = face, str(face.model.root), env, camera, spp
        self.cache_bytes = getattr(face.model, "cache_bytes", 4 << 30)
        self.method = lit_by(face)

    def __getstate__(self):
        return {**self.__dict__, "_face": None}

    def face(self):
        if self._face is None:
            from ..rendering.api import load_model

            stamp = os.stat(Path(self.root) / "model.json").st_mtime_ns
            self._face = worker_cached(("model", self.root, stamp, self.cache_bytes, self.method),
                                       lambda: load_model(self.root, self.cache_bytes).use_method(*self.method))
        return self._face


def lit_by(face) -> tuple[str, int | None]:
    """(method, rank) ``face``'s renderer lights its fields by (rank None for ``exact``; a renderer that
    does not say: ``exact``)."""
    method = getattr(face.renderer, "method", "exact")
    return method, (getattr(face.renderer, "rank", None) if method != "exact" else None)


def render_frame(context: FrameContext, unit: tuple) -> tuple[np.ndarray, float]:
    """One frame unit ``(f, target (T, 3), weights (T, S), parts or None)`` → (RGBA (H, W, 4), render seconds)."""
    f, target, weights, parts = unit
    face = context.face()
    t0 = time.perf_counter()
    rgba = face.renderer.render(target, weights, context.camera, context.env, spp=context.spp, seed=0, frame=f,
                                parts=parts)
    return rgba, time.perf_counter() - t0


class VideoWriter:
    """An mp4 writer (imageio-ffmpeg, H.264); frames are sRGB uint8 (H, W, 3)."""

    def __init__(self, path, fps: float):
        import imageio.v2 as iio

        self.path = Path(path)
        self.writer = iio.get_writer(str(self.path), fps=fps, codec="libx264", quality=8, macro_block_size=1,
                                     ffmpeg_log_level="error", pixelformat="yuv420p")

    def add(self, frame8: np.ndarray) -> None:
        h, w = frame8.shape[:2]
        self.writer.append_data(frame8[: h - h % 2, : w - w % 2])

    def close(self) -> None:
        self.writer.close()


def strip(rows: list[list[np.ndarray]], labels: list[str], exposure: float, path, scale: int = 1) -> Path:
    """Write a grid of linear RGB images (rows of equal-size frames), a label at the left of each row."""
    import cv2

    from ..imageio import to_srgb8, write_png

    tiles = []
    for row, label in zip(rows, labels):
        im = np.concatenate([to_srgb8(x[..., :3], exposure) for x in row], axis=1)
        if scale != 1:
            im = cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
        pad = np.full((im.shape[0], 110, 3), 255, np.uint8)
        cv2.putText(pad, label, (4, im.shape[0] // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(np.concatenate([pad, im], axis=1))
    write_png(path, np.concatenate(tiles, axis=0))
    return Path(path)


class FrameObserver:
    """What :func:`drive` tells an observer while it renders (this base class does nothing).

    :meth:`weights` once, with the §5 weights of the frames driven; then per environment :meth:`begin`,
    :meth:`frame` after every rendered frame, :meth:`end`.
    """

    def weights(self, face, frames: list[int], W: np.ndarray) -> dict:
        """Entries for ``drive.json``'s ``weights``; ``W`` (N, T, S) the weights rendered (filtered in time)."""
        return {}

    def begin(self, name: str, env, camera, folder: Path) -> None:
        """Environment ``name`` starts; ``folder`` is its output folder (``DRIVE/<name>``)."""

    def frame(self, f: int, rgba: np.ndarray, plate: np.ndarray, picked: bool) -> str | None:
        """Frame ``f`` was rendered (RGBA, linear, premultiplied) over ``plate``; ``picked``: it is in the strip.
        Returns a note for the progress bar, or None."""
        return None

    def end(self) -> tuple[dict, list[tuple[str, list]], str]:
        """Entries for the environment in ``drive.json``, strip rows ``(label, composites)`` to show above
        the render's row, and a note for the log line."""
        return {}, [], ""


def drive(track, model, out=None, envs=("sky", "interior"), camera=None, size: int | None = None, spp: int = 4,
          frames=None, exr: bool = True, video: bool = True, weight_sigma: float = 2.0, progress: bool = True,
          log=None, observer: FrameObserver | None = None, executor: Executor | None = None,
          method: str | None = None, rank: int | None = None) -> Path:
    """Drive ``model`` with ``track``; returns the output folder (see the module docstring).

    ``method``/``rank``: light the fields by a compression method (``sh`` 3: the copy ``mifacerf compress``
    wrote; :meth:`.rendering.api.FaceModel.use_method`); None: the model's renderer as it is (``exact`` for
    a folder).

    ``executor`` (:mod:`mifacerf.execution`; default: this process) renders the frames, one unit each
    (:func:`render_frame`); everything else stays in this process and sees the whole sequence in order:
    the weights filtered over the whole span, one exposure per environment (its first frame's), the
    PNG/EXR frames, the coherence, the observer and one video. A run split over workers writes the same
    files as one process."""
    tr = track if isinstance(track, Track) else Track(track)
    target = Path(out) if out is not None else tr.root / "drive"
    # one transaction: written beside the folder, swapped in when complete (a second drive on it: exit 3)
    with OutputFolder(target, "drive.json", TrackError, what="drive") as output:
        _drive(tr, model, output.root, envs, camera, size, spp, frames, exr, video, weight_sigma, progress, log,
               observer, executor, method, rank)
        output.finish()
    return target


def _drive(tr, model, out, envs, camera, size, spp, frames, exr, video, weight_sigma, progress, log, observer,
           executor, method=None, rank=None) -> None:
    """:func:`drive`'s work, written into ``out`` (the new folder, swapped in by the caller)."""
    from tqdm.auto import tqdm

    from ..imageio import to_srgb8, write_exr, write_png
    from ..rendering.api import composite, environment_plate, load_model

    face = model if hasattr(model, "renderer") else load_model(model)
    if method is not None:
        face.use_method(method, rank)
    if frames is None:
        fl = list(range(tr.n_frames))
    elif isinstance(frames, (tuple, list)):
        step = int(frames[2]) if len(frames) > 2 else 1
        fl = list(range(max(0, int(frames[0])), min(int(frames[1]), tr.n_frames), max(1, step)))
    else:
        fl = list(range(min(int(frames), tr.n_frames)))
    if not fl:
        raise ValueError(f"no frames to drive (the track has {tr.n_frames})")
    n = len(fl)
    V = tr.vertices
    if V.shape[1] != face.model.n_vertices:
        raise ValueError(f"the track has {V.shape[1]} template vertices, the model {face.model.n_vertices}")
    cam = face.camera(camera, size)

    # §5 weights per frame (per vertex and region) — the same call FaceModel.render(mesh=...) makes
    t0 = time.perf_counter()
    span = list(range(fl[0], fl[-1] + 1))            # weights of every frame in the span: the filter needs them
    W_span = np.stack([face.target(mesh=V[f])[1] for f in span])
    pick = [f - fl[0] for f in fl]
    W_raw, W = W_span[pick], smooth_weights(W_span, weight_sigma)[pick]
    weights_s = (time.perf_counter() - t0) / len(span)
    tmp = out / ".weights.tmp.npz"
    np.savez_compressed(tmp, weights=W.astype(np.float16), weights_unsmoothed=W_raw.astype(np.float16),
                        frames=np.array(fl), expressions=np.array(face.expressions))
    os.replace(tmp, out / "weights.npz")

    meta = {"format": FORMAT, "version": 1, "track": str(tr.root.resolve()), "model": str(Path(face.model.root).resolve()),
            "camera": cam.to_dict(), "n_frames": n, "frames": [fl[0], fl[-1] + 1],
            "frame_step": fl[1] - fl[0] if n > 1 else 1, "fps": tr.fps, "spp": spp,
            "method": dict(zip(("name", "rank"), lit_by(face))),
            "environments": {},
            "weights": {"seconds_per_frame": round(weights_s, 4), "temporal_sigma_frames": weight_sigma,
                        "coherence": weight_summary(W), "coherence_unsmoothed": weight_summary(W_raw)}}
    if observer is not None:
        meta["weights"].update(observer.weights(face, fl, W))

    base = {}
    if getattr(face.model, "references", None):
        from ..rendering.parts import part_transforms

        s0 = face.model.expression_index(face.model.neutral)
        base = part_transforms(face.model.template, face.model.eye_centres[s0], face.model.teeth[s0],
                               face.model.head_pose[s0])
    picks = {fl[k] for k in np.unique(np.linspace(0, n - 1, min(6, n)).round().astype(int))}
    rows, labels, exposure = [], [], None
    for env_name in envs:
        env = face.environment(env_name)
        ename = Path(str(env_name)).stem
        edir = out / ename
        (edir / "frames").mkdir(parents=True, exist_ok=True)
        plate = environment_plate(env, cam)
        vw = VideoWriter(edir / "performance.mp4", tr.fps) if video else None
        coh = PixelCoherence()
        times = {"render": [], "composite_write": []}
        strip_r = []
        if observer is not None:
            observer.begin(ename, env, cam, edir)
        bar = tqdm(total=n, desc=f"drive {ename}", unit="frame", disable=not progress)
        env_exposure = None
        units = [(f, V[f], W[k], frame_parts(face, tr, f, base) if base else None) for k, f in enumerate(fl)]
        rendered = (executor or Executor()).imap(render_frame, units, FrameContext(face, env, cam, spp))
        for k, (f, (rgba, render_s)) in enumerate(zip(fl, rendered)):   # in frame order, wherever rendered
            t1 = time.perf_counter()
            rgb = composite(rgba, plate)
            if env_exposure is None:
                env_exposure = exposure_for(rgba)
            write_png(edir / "frames" / f"F{f:05d}.png", rgb, exposure=env_exposure)
            if exr:
                write_exr(edir / "frames" / f"F{f:05d}.exr", rgba)
            if vw is not None:
                vw.add(to_srgb8(rgb, env_exposure))
            coh.add(rgba)
            t2 = time.perf_counter()
            times["render"].append(render_s)
            times["composite_write"].append(t2 - t1)
            note = observer.frame(f, rgba, plate, f in picks) if observer is not None else None
            if f in picks:
                strip_r.append(rgb)
            bar.update(1)
            if note:
                bar.set_postfix_str(note)
        bar.close()
        if vw is not None:
            vw.close()
        exposure = exposure or env_exposure
        e = {"render_seconds_per_frame": round(float(np.mean(times["render"])), 4),
             "write_seconds_per_frame": round(float(np.mean(times["composite_write"])), 4),
             "pixel_coherence": coh.summary(), "exposure": env_exposure,
             "video": str((edir / "performance.mp4").relative_to(out)) if video else None}
        extra, above, note = observer.end() if observer is not None else ({}, [], "")
        e.update(extra)
        rows += [r for _, r in above] + [strip_r]
        labels += [lab for lab, _ in above] + [f"render {ename}"]
        meta["environments"][ename] = e
        write_json_atomic(out / "drive.json", meta)
        if log:
            log(f"{ename}: {n} frames, render {e['render_seconds_per_frame']:.2f} s/frame" + note)
    if rows:
        strip(rows, labels, exposure or 1.0, out / "strip.png")
        meta["strip"] = "strip.png"
        meta["strip_frames"] = sorted(int(p) for p in picks)
    write_json_atomic(out / "drive.json", meta)
