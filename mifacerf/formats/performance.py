"""The performance folder: a multi-view video of a performance, and the only input of tracking.

Layout (docs/tracking.md)::

    PERF/
      manifest.json                       written last: its presence means "complete"
      frames/<camera>/F<frame:05d>.exr    one image per camera and video frame (OpenEXR half, linear RGB)
      hand/template.json                  the template the user built on the neutral (mifacerf.template/1)
      hand/keyframes.json                 which frames were hand-marked, and for what (lips, eyelids, irises)
      hand/rotoscope/F<frame:05d>.json    one keyframe's marks, in the registration's rotoscope format

``manifest.json``::

    {"format": "mifacerf.performance", "version": 1,
     "fps": 60.0, "n_frames": N,
     "cameras": [Camera.to_dict(), ...],          # calibrated, OpenCV conventions, video resolution
     "frame_pattern": "frames/{camera}/F{frame:05d}.exr",
     "lighting": {...},                           # how the subject was lit (documentation only)
     "template": "hand/template.json",
     "starts_at_rest": true,                      # frame 0 shows the neutral face, head at the neutral pose
     "subject": {...}, "dot_radius": 0.0015}

Version 2 adds ``"checksums": {"frames/<camera>/F<frame>.exr": sha256}`` of every frame
(written with the manifest, last) and ``"sizes"`` (bytes per frame; absent in folders written
before it). What a frame held when it was recorded — a camera's own faults included: a garbled
file, a dark or duplicated image — is what the checksum certifies, and tracking treats a frame it
cannot decode as dropped and reports it. Later damage is an error naming the file: opening checks
the size of every recorded frame present (one ``stat`` each; a frame missing is a dropped one),
:meth:`PerformanceFolder.read` checksums a frame the first time it reads it (once per process),
and :meth:`PerformanceFolder.verify` (``mifacerf verify PERF``) checks every frame. Every key
above but ``lighting``, ``starts_at_rest``, ``subject`` and ``dot_radius`` is required.
Recording is resumable: frames already on disk are kept, but only when the recording's
settings (cameras, fps, frame count, extras) are those the folder was started with
(``.recording.json``); other settings are refused rather than mixed with those frames.

Frames are synchronised (genlocked): file ``F00042`` of every camera was exposed at
``42 / fps`` seconds. A camera that dropped a frame simply lacks that file; a duplicated
frame is a file identical to the previous one (tracking detects both, see :mod:`mifacerf.tracking.health`).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..imageio import ImageFileError, read_exr, write_exr
from ..errors import MifacerfError
from .files import FolderLock, read_json, read_json_manifest, require_keys, sha256_file, write_json_atomic

FORMAT = "mifacerf.performance"
VERSION = 2
READS = (1, 2)            #: versions this reader opens (1: before the checksums)
#: keys the manifest must hold (version 1 lacks "checksums")
REQUIRED = ("cameras", "fps", "n_frames", "frame_pattern", "template", "checksums")
FRAME_PATTERN = "frames/{camera}/F{frame:05d}.exr"
KEYFRAMES_FORMAT = "mifacerf.performance_keyframes"


class PerformanceError(MifacerfError, ValueError):
    """A missing or inconsistent performance folder; the message names the file."""


class PerformanceFolder:
    """A performance folder opened for reading (frames are read on demand)."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        path = self.root / "manifest.json"
        self.meta = read_json_manifest(path, FORMAT, READS, PerformanceError,
                                       "missing (not a performance folder, or its recording did not finish)",
                                       f"{FORMAT} manifest")
        require_keys(self.meta, REQUIRED if self.meta["version"] >= 2 else REQUIRED[:-1], str(path),
                     PerformanceError)
        #: {relative path: sha256} of every frame (None: version 1, unchecked)
        self.checksums: dict | None = self.meta.get("checksums")
        try:
            self.cameras = [Camera.from_dict(c) for c in self.meta["cameras"]]
            self.fps = float(self.meta["fps"])
            self.n_frames = int(self.meta["n_frames"])
        except (KeyError, ValueError, TypeError) as exc:
            raise PerformanceError(f"{path}: needs cameras, fps and n_frames ({exc})") from exc
        if len(self.cameras) < 2:
            raise PerformanceError(f"{path}: tracking needs at least two cameras")
        self.pattern = self.meta["frame_pattern"]
        self._verified: set[str] = set()
        sizes = self.meta.get("sizes") if self.checksums is not None else None
        for rel, size in (sizes or {}).items():
            try:
                now = (self.root / rel).stat().st_size
            except FileNotFoundError:
                continue                  # a dropped frame (verify reports it)
            if now != size:
                raise PerformanceError(f"{self.root / rel}: {now} bytes, the manifest says {size} (the file "
                                       "changed after the recording or is truncated)")

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def frame_path(self, camera: str, frame: int) -> Path:
        return self.root / self.pattern.format(camera=camera, frame=frame)

    def read(self, camera: str, frame: int) -> np.ndarray | None:
        """The (H, W, 3) image of ``camera`` at ``frame``, or None when the file is missing or unreadable."""
        cam = self.cameras[self.camera_names.index(camera)]
        path = self.frame_path(camera, frame)
        if self.checksums is not None and path.exists():
            self.check_frame(path)
        try:
            return read_exr(path, channels=3, expect_shape=(cam.height, cam.width))
        except ImageFileError:
            return None

    def check_frame(self, path: Path) -> None:
        """Checksum a frame against the manifest, once per process and file (no-op for version 1):
        :class:`PerformanceError` naming it when it changed or was added after the recording."""
        if self.checksums is None:
            return
        rel = Path(path).relative_to(self.root).as_posix()
        if rel in self._verified:
            return
        self._check(Path(path))
        self._verified.add(rel)

    def _check(self, path: Path) -> None:
        rel = path.relative_to(self.root).as_posix()
        want = self.checksums.get(rel)
        if want is None:
            raise PerformanceError(f"{path}: not in the manifest's checksums (a frame added after the recording)")
        if sha256_file(path) != want:
            raise PerformanceError(f"{path}: checksum mismatch (the file changed after the recording or is "
                                   "corrupt; restore it, or delete it to track without it, as a dropped frame)")

    def verify(self) -> list[str]:
        """Every problem found by checking each recorded frame's checksum (empty: all verify)."""
        if self.checksums is None:
            return [f"{self.root / 'manifest.json'}: a version-1 performance without checksums"]
        problems = []
        for rel in sorted(self.checksums):
            p = self.root / rel
            try:
                if not p.exists():
                    raise PerformanceError(f"{p}: missing (listed in the manifest)")
                self._check(p)
            except PerformanceError as exc:
                problems.append(str(exc))
        return problems

    @property
    def template_path(self) -> Path:
        return self.root / self.meta.get("template", "hand/template.json")

    def template(self) -> dict:
        p = self.template_path
        if not p.exists():
            raise PerformanceError(f"{p}: missing (the template built on the neutral)")
        return json.loads(p.read_text())

    def keyframes(self) -> dict:
        """{"lips": [frames], "eyelids": [frames], "irises": [frames]} (empty lists when none were marked)."""
        p = self.root / "hand" / "keyframes.json"
        if not p.exists():
            return {"lips": [], "eyelids": [], "irises": []}
        d = json.loads(p.read_text())
        return {k: sorted(int(f) for f in d.get(k, [])) for k in ("lips", "eyelids", "irises")}


class PerformanceWriter:
    """Writes a performance folder; :meth:`finish` writes the manifest (completion marker) last.

    The folder's lock (``.<name>.lock`` beside it) is held from construction to :meth:`finish` (or until
    the writer is dropped): a second recording into the same folder is refused at once (exit 3).
    """

    def __init__(self, root: str | os.PathLike, cameras: list[Camera], fps: float, n_frames: int,
                 template: dict, extra: dict | None = None):
        import weakref

        self.root = Path(root)
        self._lock = FolderLock(self.root, PerformanceError, wait=False, what="performance recording").acquire()
        self._unlock = weakref.finalize(self, self._lock.release)
        try:
            self._start(cameras, fps, n_frames, template, extra)
        except BaseException:
            self._unlock()
            raise

    def _start(self, cameras, fps, n_frames, template, extra) -> None:
        self.cameras = cameras
        self.meta = {"format": FORMAT, "version": VERSION, "fps": float(fps), "n_frames": int(n_frames),
                     "cameras": [c.to_dict() for c in cameras], "frame_pattern": FRAME_PATTERN,
                     "template": "hand/template.json", **(extra or {})}
        # resume only what was started with the same settings (the frames on disk belong to them)
        settings = json.loads(json.dumps({**self.meta, "template_content": template}))
        stamp = self.root / ".recording.json"
        if stamp.exists():
            before = read_json(stamp, PerformanceError, "missing")
        elif (self.root / "manifest.json").exists():     # a complete recording of an earlier version
            before = {k: v for k, v in read_json(self.root / "manifest.json", PerformanceError, "missing").items()
                      if k not in ("checksums", "sizes")}
            before.update(version=VERSION, template_content=read_json(self.root / "hand" / "template.json",
                                                                      PerformanceError, "missing"))
        elif any((self.root / "frames").rglob("*.exr")):
            raise PerformanceError(f"{self.root}: holds frames of an unknown recording; record into a new folder, "
                                   "or delete this one to start again")
        else:
            before = settings
        if before != settings:
            diff = sorted(k for k in set(before) | set(settings) if before.get(k) != settings.get(k))
            raise PerformanceError(f"{self.root}: holds frames recorded with other settings ({', '.join(diff)} "
                                   "differ); record into a new folder, or delete this one to start again")
        for c in cameras:
            (self.root / "frames" / c.name).mkdir(parents=True, exist_ok=True)
        (self.root / "hand" / "rotoscope").mkdir(parents=True, exist_ok=True)
        write_json_atomic(self.root / "hand" / "template.json", template)
        write_json_atomic(stamp, settings)

    def frame_path(self, camera: str, frame: int) -> Path:
        return self.root / FRAME_PATTERN.format(camera=camera, frame=frame)

    def has_frame(self, frame: int) -> bool:
        return all(self.frame_path(c.name, frame).exists() for c in self.cameras)

    def write(self, camera: str, frame: int, image: np.ndarray) -> None:
        write_exr(self.frame_path(camera, frame), np.asarray(image)[..., :3])

    def write_keyframes(self, index: dict, marks: dict) -> None:
        """``index`` {"lips"/"eyelids"/"irises": [frames]}; ``marks`` {frame: rotoscope dict}."""
        for f, d in marks.items():
            write_json_atomic(self.root / "hand" / "rotoscope" / f"F{int(f):05d}.json", d)
        write_json_atomic(self.root / "hand" / "keyframes.json",
                          {"format": KEYFRAMES_FORMAT, "version": 1,
                           **{k: sorted(int(f) for f in v) for k, v in index.items()}})

    def finish(self) -> Path:
        """Checksum every frame on disk and write the manifest (the completion marker), last."""
        frames = sorted(p for c in self.cameras for p in (self.root / "frames" / c.name).glob("F*.exr"))
        self.meta["checksums"] = {p.relative_to(self.root).as_posix(): sha256_file(p) for p in frames}
        self.meta["sizes"] = {p.relative_to(self.root).as_posix(): p.stat().st_size for p in frames}
        write_json_atomic(self.root / "manifest.json", self.meta)
        self._unlock()
        return self.root
