"""The capture folder: what a light stage writes, and the only input of registration.

Layout (documented for users in docs/capture-format.md)::

    CAPTURE/
      manifest.json                                   written last: its presence means "complete"
      images/<expression>/<camera>/L<light:03d>.exr   one OLAT image per expression, camera, light
      hand/                                           hand-made registration inputs (template, clicks)
      cache/<expression>/<camera>.npy                 packed fields, built on demand (may be deleted)

Images are OpenEXR half float RGB, as the camera recorded them: linear camera RGB of
the subject lit by one strobe. :meth:`Capture.image` and :meth:`Capture.field`
return **calibrated** data: ``radiance = M @ (linearise(pixel) / exposure) / E_l``
with the camera's radiometric calibration (``M`` 3x3 colour matrix to linear sRGB,
``exposure``, optional response curve) and the light's irradiance ``E_l`` (RGB), so
every value is linear-sRGB radiance per unit irradiance (docs/conventions.md).

Reading is lazy: opening reads the manifest only; pixels are read when asked for,
one file per (expression, camera, light). Every missing, truncated or inconsistent
file raises :class:`CaptureError` naming the file and the problem.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..imageio import ImageFileError, read_exr, write_exr
from ..rig import Rig
from ..errors import MifacerfError
from .files import read_json, require_keys, save_npy_atomic, sha256_file, write_json_atomic

FORMAT = "mifacerf.capture"
VERSION = 1
IMAGE_PATTERN = "images/{expression}/{camera}/L{light:03d}.exr"
CATEGORIES = ("neutral", "emotion", "viseme", "mouth", "head_pose", "eyes", "coverage", "other")
#: keys a manifest must hold (CaptureWriter writes them all; units, colour_space and frames are
#: documentation and may be absent)
REQUIRED = ("rig", "expressions", "image_pattern", "checksums")
LIGHT_KEYS = ("index", "direction", "solid_angle", "irradiance", "arm_position", "strobe")
CAMERA_KEYS = ("name", "width", "height", "K", "dist", "R", "t", "radiometry")


class CaptureError(MifacerfError, ValueError):
    """A capture folder that is missing, incomplete or inconsistent; the message names the file."""


@dataclass
class ExpressionEntry:
    """One captured expression: ``name`` (unique, a folder name), ``category`` (one of CATEGORIES)."""

    name: str
    category: str = "other"

    def to_dict(self) -> dict:
        return {"name": self.name, "category": self.category}


@dataclass
class Radiometry:
    """A camera's radiometric calibration (camera RGB → linear sRGB radiance).

    ``exposure``: recorded value per unit radiance; ``colour_matrix`` (3, 3): applied
    after linearisation and exposure; ``response``: None (linear) or a dict
    ``{"x": [...], "y": [...]}`` — a monotone curve mapping recorded values (x) to
    linear values (y), applied by linear interpolation; ``y`` is one curve for all
    channels (n,) or one per channel (3, n) in R, G, B order.
    """

    exposure: float = 1.0
    colour_matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    response: dict | None = None

    def __post_init__(self):
        self.colour_matrix = np.asarray(self.colour_matrix, np.float64).reshape(3, 3)
        if not (np.isfinite(self.exposure) and self.exposure > 0):
            raise ValueError(f"exposure must be positive, got {self.exposure}")
        if self.response is not None:
            x, y = np.asarray(self.response["x"]), np.asarray(self.response["y"])
            if x.ndim != 1 or np.any(np.diff(x) <= 0) or y.shape[-1] != len(x) or y.ndim not in (1, 2) \
                    or (y.ndim == 2 and len(y) != 3):
                raise ValueError("response curve needs increasing x and y of shape (n,) or (3, n)")

    @property
    def is_identity(self) -> bool:
        return self.exposure == 1.0 and self.response is None and np.array_equal(self.colour_matrix, np.eye(3))

    def apply(self, image: np.ndarray) -> np.ndarray:
        """Recorded (..., 3) → calibrated linear sRGB (..., 3), float32."""
        img = np.asarray(image, np.float32)
        if self.is_identity:
            return img
        if self.response is not None:
            x = np.asarray(self.response["x"], np.float64)
            y = np.asarray(self.response["y"], np.float64)
            if y.ndim == 1:
                img = np.interp(img, x, y).astype(np.float32)
            else:
                img = np.stack([np.interp(img[..., c], x, y[c]) for c in range(3)], axis=-1).astype(np.float32)
        img = img / np.float32(self.exposure)
        return (img @ self.colour_matrix.T.astype(np.float32)).astype(np.float32)

    def to_dict(self) -> dict:
        return {"exposure": self.exposure, "colour_matrix": self.colour_matrix.tolist(),
                "response": self.response}

    @classmethod
    def from_dict(cls, d: dict | None) -> "Radiometry":
        d = d or {}
        return cls(d.get("exposure", 1.0), d.get("colour_matrix", np.eye(3)), d.get("response"))


class Capture:
    """A capture folder opened for reading. Nothing but the manifest is read on open."""

    def __init__(self, root: str | os.PathLike):
        self.root = Path(root)
        mpath = self.root / "manifest.json"
        if not self.root.is_dir():
            raise CaptureError(f"{self.root}: no such capture folder")
        self.manifest = read_json(mpath, CaptureError, "missing; the capture is incomplete (the manifest is written last)")
        self._validate(mpath)

    # ------------------------------------------------------------- validation
    def _validate(self, mpath: Path) -> None:
        m = self.manifest
        if m.get("format") != FORMAT:
            raise CaptureError(f"{mpath}: not a mifacerf capture manifest (format={m.get('format')!r})")
        if m.get("version") != VERSION:
            raise CaptureError(f"{mpath}: unsupported version {m.get('version')!r} (this is {VERSION})")
        self._require_keys(mpath)
        try:
            self.rig = Rig.from_dict(m["rig"])
        except (KeyError, ValueError, TypeError) as exc:
            raise CaptureError(f"{mpath}: invalid rig description ({exc})") from exc
        if len(self.rig.lights) == 0 or not self.rig.cameras:
            raise CaptureError(f"{mpath}: the rig has no lights or no cameras")
        names = [c.name for c in self.rig.cameras]
        if len(set(names)) != len(names):
            raise CaptureError(f"{mpath}: duplicate camera names {names}")
        self.radiometry = {}
        for c in m["rig"]["cameras"]:
            try:
                self.radiometry[c["name"]] = Radiometry.from_dict(c["radiometry"])
            except (ValueError, KeyError) as exc:
                raise CaptureError(f"{mpath}: camera {c['name']}: bad radiometry ({exc})") from exc
        self.expressions = []
        for e in m["expressions"]:
            cat = e["category"]
            if cat not in CATEGORIES:
                raise CaptureError(f"{mpath}: expression {e['name']!r} has unknown category {cat!r}")
            self.expressions.append(ExpressionEntry(e["name"], cat))
        enames = [e.name for e in self.expressions]
        if len(set(enames)) != len(enames):
            raise CaptureError(f"{mpath}: duplicate expression names")
        if not enames:
            raise CaptureError(f"{mpath}: no expressions")
        self.pattern = m["image_pattern"]
        self.checksums = m["checksums"]

    def _require_keys(self, mpath: Path) -> None:
        """Every key the writer writes and the reader uses: a missing one is an error naming it (no
        default stands in for a deleted calibration)."""
        m, where = self.manifest, str(mpath)
        require_keys(m, REQUIRED, where, CaptureError)
        require_keys(m["rig"], ("lights", "cameras"), f"{where}: rig", CaptureError)
        require_keys(m["rig"]["lights"], ("layout", "lights"), f"{where}: rig.lights", CaptureError)
        require_keys(m["rig"]["lights"]["layout"], ("n_positions", "n_strobes"), f"{where}: rig.lights.layout",
                     CaptureError)
        for i, light in enumerate(m["rig"]["lights"]["lights"]):
            require_keys(light, LIGHT_KEYS, f"{where}: light {i}", CaptureError)
        for i, cam in enumerate(m["rig"]["cameras"]):
            require_keys(cam, CAMERA_KEYS, f"{where}: camera {i}", CaptureError)
            require_keys(cam["radiometry"], ("exposure", "colour_matrix", "response"),
                         f"{where}: camera {cam['name']!r} radiometry", CaptureError)
        if not isinstance(m["expressions"], list):
            raise CaptureError(f"{where}: 'expressions' must be a list")
        for i, e in enumerate(m["expressions"]):
            require_keys(e, ("name", "category"), f"{where}: expression entry {i}", CaptureError)

    # ------------------------------------------------------------------ access
    @property
    def expression_names(self) -> list[str]:
        return [e.name for e in self.expressions]

    @property
    def camera_names(self) -> list[str]:
        return [c.name for c in self.rig.cameras]

    @property
    def n_lights(self) -> int:
        return len(self.rig.lights)

    def expression_index(self, name: str) -> int:
        try:
            return self.expression_names.index(name)
        except ValueError:
            raise KeyError(f"{self.root}: no expression named {name!r}") from None

    def image_path(self, expression: str, camera: str, light: int) -> Path:
        return self.root / self.pattern.format(expression=expression, camera=camera, light=int(light))

    def _check_key(self, expression: str, camera: str, light: int | None = None) -> None:
        self.expression_index(expression)
        self.rig.camera(camera)
        if light is not None and not 0 <= int(light) < self.n_lights:
            raise KeyError(f"light {light} out of range (capture has {self.n_lights})")

    def raw_image(self, expression: str, camera: str, light: int) -> np.ndarray:
        """The recorded image (H, W, 3) float32, uncalibrated, as on disk."""
        self._check_key(expression, camera, light)
        cam = self.rig.camera(camera)
        path = self.image_path(expression, camera, light)
        rel = path.relative_to(self.root).as_posix()
        if rel in self.checksums and path.exists() and sha256_file(path) != self.checksums[rel]:
            raise CaptureError(f"{path}: checksum mismatch (the file changed or is corrupt)")
        try:
            return read_exr(path, channels=3, expect_shape=(cam.height, cam.width))
        except ImageFileError as exc:
            raise CaptureError(str(exc)) from exc

    def image(self, expression: str, camera: str, light: int) -> np.ndarray:
        """Calibrated radiance per unit irradiance (H, W, 3) float32 for one light."""
        img = self.radiometry[camera].apply(self.raw_image(expression, camera, light))
        return img / self.rig.lights.irradiance[int(light)].astype(np.float32)

    def cache_path(self, expression: str, camera: str) -> Path:
        return self.root / "cache" / expression / f"{camera}.npy"

    def field(self, expression: str, camera: str, lights=None, use_cache: bool = True,
              progress: bool = False) -> np.ndarray:
        """The reflectance field of one (expression, camera): (L', H, W, 3) float32, calibrated.

        ``lights``: indices to read (default all); only those files are read (``progress``: a bar over
        them). When a
        packed cache exists (see :meth:`build_cache`) and is current it is memory-mapped
        instead, and only the requested lights are touched.
        """
        self._check_key(expression, camera)
        idx = np.arange(self.n_lights) if lights is None else np.asarray(lights, np.int64).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_lights):
            raise KeyError(f"light index out of range (capture has {self.n_lights})")
        cpath = self.cache_path(expression, camera)
        cam = self.rig.camera(camera)
        if use_cache and cpath.exists() and self._cache_current(expression, camera):
            try:
                packed = np.load(cpath, mmap_mode="r")
                if packed.shape == (self.n_lights, cam.height, cam.width, 3):
                    return np.asarray(packed[idx], np.float32)
            except (OSError, ValueError, EOFError):
                pass                  # a damaged cache: read the images (the cache may always be deleted)
        out = np.empty((len(idx), cam.height, cam.width, 3), np.float32)
        if progress:
            from ..progress import bar

            idx = bar(idx, desc=f"{expression}/{camera}", unit="light")
        for i, l in enumerate(idx):
            out[i] = self.image(expression, camera, int(l))
        return out

    def _cache_stamp(self, expression: str, camera: str) -> list:
        stamp = []
        for l in range(self.n_lights):
            p = self.image_path(expression, camera, l)
            try:
                st = p.stat()
            except FileNotFoundError:
                raise CaptureError(f"{p}: missing image file") from None
            stamp.append([st.st_size, st.st_mtime_ns])
        return stamp

    def _cache_current(self, expression: str, camera: str) -> bool:
        side = self.cache_path(expression, camera).with_suffix(".json")
        try:
            return json.loads(side.read_text()) == {"stamp": self._cache_stamp(expression, camera),
                                                    "calibration": self._calibration_key(camera)}
        except (FileNotFoundError, json.JSONDecodeError):
            return False

    def _calibration_key(self, camera: str) -> str:
        data = json.dumps([self.radiometry[camera].to_dict(), self.rig.lights.irradiance.tolist()])
        return hashlib.sha1(data.encode()).hexdigest()

    def build_cache(self, expression: str, camera: str, progress: bool = False) -> Path:
        """Pack one (expression, camera) field into ``cache/<expression>/<camera>.npy`` (float16, calibrated;
        ``progress``: a bar over the lights)."""
        field_ = self.field(expression, camera, use_cache=False, progress=progress)
        if np.abs(field_).max(initial=0) > 65504:
            raise CaptureError(f"{expression}/{camera}: values overflow the float16 cache")
        path = self.cache_path(expression, camera)
        save_npy_atomic(path, field_.astype(np.float16))
        write_json_atomic(path.with_suffix(".json"), {"stamp": self._cache_stamp(expression, camera),
                                                      "calibration": self._calibration_key(camera)})
        return path

    def verify(self, checksums: bool = True) -> list[str]:
        """Check that every expected image exists (and matches its checksum); returns the problems found."""
        problems = []
        for e in self.expression_names:
            for c in self.camera_names:
                for l in range(self.n_lights):
                    p = self.image_path(e, c, l)
                    rel = p.relative_to(self.root).as_posix()
                    if not p.exists():
                        problems.append(f"{p}: missing image file")
                    elif checksums and rel in self.checksums and sha256_file(p) != self.checksums[rel]:
                        problems.append(f"{p}: checksum mismatch")
        return problems


class CaptureWriter:
    """Writes a capture folder so that it is never left looking complete while it is not.

    Images go through :func:`mifacerf.imageio.write_exr` (temporary name, fsync,
    rename); ``manifest.json`` is written by :meth:`finish` after everything else. An
    existing complete capture is never overwritten unless ``overwrite=True``.
    """

    def __init__(self, root: str | os.PathLike, rig: Rig, expressions: list[ExpressionEntry],
                 radiometry: dict[str, Radiometry] | None = None, extra: dict | None = None,
                 overwrite: bool = False, record_checksums: bool = True):
        self.root = Path(root)
        if (self.root / "manifest.json").exists() and not overwrite:
            raise CaptureError(f"{self.root}: already holds a complete capture (manifest.json); "
                               "choose another folder or allow overwriting")
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            probe = self.root / ".write-test"
            probe.write_bytes(b"")
            probe.unlink()
        except OSError as exc:
            raise CaptureError(f"{self.root}: cannot write the capture here ({exc.strerror or exc})") from exc
        if overwrite and (self.root / "manifest.json").exists():
            (self.root / "manifest.json").unlink()
        self.rig = rig
        self.expressions = list(expressions)
        names = [e.name for e in self.expressions]
        if len(set(names)) != len(names):
            raise CaptureError("duplicate expression names")
        for e in self.expressions:
            if e.category not in CATEGORIES:
                raise CaptureError(f"expression {e.name!r}: unknown category {e.category!r}")
        self.radiometry = radiometry or {c.name: Radiometry() for c in rig.cameras}
        self.extra = extra or {}
        self.record_checksums = record_checksums
        self.checksums: dict[str, str] = {}

    def image_path(self, expression: str, camera: str, light: int) -> Path:
        return self.root / IMAGE_PATTERN.format(expression=expression, camera=camera, light=int(light))

    def write_image(self, expression: str, camera: str, light: int, image: np.ndarray) -> Path:
        """Write one recorded image (H, W, 3) atomically; NaN/Inf pixels raise."""
        cam = self.rig.camera(camera)
        if image.shape[:2] != (cam.height, cam.width):
            raise CaptureError(f"{expression}/{camera}/L{light:03d}: image is {image.shape[:2]}, "
                               f"camera is {cam.height}x{cam.width}")
        path = self.image_path(expression, camera, light)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_exr(path, image)
        if self.record_checksums:
            self.checksums[path.relative_to(self.root).as_posix()] = sha256_file(path)
        return path

    def manifest(self) -> dict:
        rig = self.rig.to_dict()
        for c in rig["cameras"]:
            c["radiometry"] = self.radiometry[c["name"]].to_dict()
        return {
            "format": FORMAT, "version": VERSION,
            "units": {"length": "metre", "angle": "radian",
                      "images": "linear camera RGB as recorded; calibrated radiance per unit irradiance = "
                                "colour_matrix @ (response(pixel) / exposure) / light irradiance"},
            "colour_space": "linear sRGB (Rec. 709 primaries, D65 white)",
            "frames": "world: metres, +Y up, +Z from the head towards the cameras, +X the subject's left; "
                      "cameras: OpenCV (x_cam = R x_world + t, +y down, pixel centres at integers); "
                      "light directions point from the subject to the light (docs/conventions.md)",
            "image_pattern": IMAGE_PATTERN,
            "rig": rig,
            "expressions": [e.to_dict() for e in self.expressions],
            "checksums": self.checksums,
            **self.extra,
        }

    def finish(self) -> Path:
        """Check every image is present, then write ``manifest.json`` (atomically, last)."""
        missing = [str(self.image_path(e.name, c.name, l)) for e in self.expressions for c in self.rig.cameras
                   for l in range(len(self.rig.lights)) if not self.image_path(e.name, c.name, l).exists()]
        if missing:
            raise CaptureError(f"capture incomplete: {len(missing)} image(s) missing, e.g. {missing[0]}")
        path = self.root / "manifest.json"
        write_json_atomic(path, self.manifest())
        return path
