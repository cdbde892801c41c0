"""The registration folder: registration's output, the model build's input.

Layout (default ``CAPTURE/registration/``)::

    registration.json                  format, version, the capture it belongs to, per-expression report
    template.json                      the template used (a copy of CAPTURE/hand/template.json)
    expressions/<expression>.npz       registered geometry of one expression (below)
    dotfree/<expression>/<camera>.npz  dot removal: replacement pixels for every light (below)

``expressions/<name>.npz`` (all world frame, metres):
  ``vertices`` (T, 3) float64 template vertex positions;
  ``status`` (T,) int8: 1 registered (snapped to a dot / placed from the data),
  0 predicted only (no dot found: the morph prediction, flagged, never presented as
  data), -1 failed (no usable estimate; position is the prediction);
  ``uv`` (C, T, 2) float32 projection of every vertex into every camera (pixels,
  OpenCV convention, lens distortion included) — the texture coordinates of the
  expression's reflectance fields;
  ``visible`` (C, T) bool per-vertex visibility in each camera (ray-traced against
  the expression's own registered mesh);
  ``eye_centres`` (2, 3) left, right eyeball centres (NaN if the template has no eyes);
  ``teeth`` (2, 4, 4) rigid transforms (template teeth frame → world) of the upper and
  lower teeth (NaN if none);
  ``head_pose`` (4, 4) rigid transform (neutral head → this expression).

``dotfree/<expression>/<camera>.npz``: ``pixels`` (N, 2) int32 (row, column) of the
pixels the dot removal changed and ``values`` (L, N, 3) float16, their calibrated
radiance per unit irradiance for every light. Unchanged pixels are read from the
capture, so the dot-free field costs only the patched pixels.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .capture import Capture
from .files import read_json_manifest, write_json_atomic

FORMAT = "mifacerf.registration"
VERSION = 1


class RegistrationError(ValueError):
    """A missing or inconsistent registration folder; the message names the file."""


def _save_npz_atomic(path: Path, **arrays) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez_compressed(tmp, **arrays)
    os.replace(tmp, path)


class RegisteredExpression:
    """One expression's registered geometry (see the module docstring for the arrays)."""

    def __init__(self, name: str, vertices, status, uv, visible, eye_centres=None, teeth=None, head_pose=None):
        self.name = name
        self.vertices = np.asarray(vertices, np.float64)
        t = len(self.vertices)
        self.status = np.asarray(status, np.int8).reshape(t)
        self.uv = np.asarray(uv, np.float32)
        self.visible = np.asarray(visible, bool)
        if self.uv.ndim != 3 or self.uv.shape[1:] != (t, 2) or self.visible.shape != self.uv.shape[:2]:
            raise RegistrationError(f"{name}: uv {self.uv.shape} / visible {self.visible.shape} do not match "
                                    f"{t} vertices")
        self.eye_centres = np.full((2, 3), np.nan) if eye_centres is None else np.asarray(eye_centres, np.float64)
        self.teeth = np.full((2, 4, 4), np.nan) if teeth is None else np.asarray(teeth, np.float64)
        self.head_pose = np.eye(4) if head_pose is None else np.asarray(head_pose, np.float64)
        if not np.isfinite(self.vertices).all():
            raise RegistrationError(f"{name}: non-finite vertex positions")

    def save(self, path: Path) -> None:
        _save_npz_atomic(path, vertices=self.vertices, status=self.status, uv=self.uv, visible=self.visible,
                         eye_centres=self.eye_centres, teeth=self.teeth, head_pose=self.head_pose)

    @classmethod
    def load(cls, path: Path, name: str) -> "RegisteredExpression":
        if not path.exists():
            raise RegistrationError(f"{path}: missing (expression {name!r} not registered)")
        try:
            z = np.load(path)
            return cls(name, z["vertices"], z["status"], z["uv"], z["visible"], z["eye_centres"], z["teeth"],
                       z["head_pose"])
        except (KeyError, ValueError, OSError, EOFError) as exc:
            raise RegistrationError(f"{path}: unreadable or incomplete ({exc})") from exc


class Registration:
    """A registration folder opened for reading (lazy: expressions and patches load on demand)."""

    def __init__(self, root: str | os.PathLike, capture: Capture | None = None):
        self.root = Path(root)
        self.meta = read_json_manifest(self.root / "registration.json", FORMAT, VERSION, RegistrationError,
                                       "missing; run 'mifacerf register' first", "mifacerf registration")
        tpath = self.root / "template.json"
        if not tpath.exists():
            raise RegistrationError(f"{tpath}: missing")
        self.template = json.loads(tpath.read_text())
        self.capture = capture if capture is not None else Capture(self._capture_path())
        self._cache: dict[str, RegisteredExpression] = {}

    def _capture_path(self) -> Path:
        p = Path(self.meta.get("capture", ".."))
        return p if p.is_absolute() else (self.root / p).resolve()

    @property
    def expression_names(self) -> list[str]:
        """Registered expressions, in capture order."""
        done = self.meta.get("expressions", {})
        return [e for e in self.capture.expression_names if e in done]

    def report(self, name: str) -> dict:
        return self.meta["expressions"][name]

    def expression(self, name: str) -> RegisteredExpression:
        if name not in self._cache:
            self._cache[name] = RegisteredExpression.load(self.root / "expressions" / f"{name}.npz", name)
        return self._cache[name]

    def dotfree_patch(self, expression: str, camera: str) -> tuple[np.ndarray, np.ndarray] | None:
        path = self.root / "dotfree" / expression / f"{camera}.npz"
        if not path.exists():
            return None
        try:
            z = np.load(path)
            return z["pixels"], z["values"]
        except (KeyError, ValueError, OSError, EOFError) as exc:
            raise RegistrationError(f"{path}: unreadable ({exc})") from exc

    def field(self, expression: str, camera: str, lights=None) -> np.ndarray:
        """The dot-free reflectance field (L', H, W, 3) float32: the capture's field with the patch applied."""
        f = self.capture.field(expression, camera, lights)
        patch = self.dotfree_patch(expression, camera)
        if patch is not None:
            pixels, values = patch
            idx = np.arange(self.capture.n_lights) if lights is None else np.asarray(lights).reshape(-1)
            f[:, pixels[:, 0], pixels[:, 1]] = values[idx].astype(np.float32)
        return f


class RegistrationWriter:
    """Writes a registration folder; ``registration.json`` is rewritten after each expression."""

    def __init__(self, root: str | os.PathLike, capture: Capture, template: dict):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.capture = capture
        path = self.root / "registration.json"
        if path.exists():
            self.meta = json.loads(path.read_text())
        else:
            rel = os.path.relpath(capture.root.resolve(), self.root.resolve())
            self.meta = {"format": FORMAT, "version": VERSION, "capture": rel, "expressions": {}}
        write_json_atomic(self.root / "template.json", template)

    def done(self, name: str) -> bool:
        return name in self.meta["expressions"] and (self.root / "expressions" / f"{name}.npz").exists()

    def write_expression(self, reg: RegisteredExpression, report: dict) -> None:
        reg.save(self.root / "expressions" / f"{reg.name}.npz")
        self.meta["expressions"][reg.name] = report
        write_json_atomic(self.root / "registration.json", self.meta)

    def write_dotfree(self, expression: str, camera: str, pixels: np.ndarray, values: np.ndarray) -> None:
        pixels = np.asarray(pixels, np.int32).reshape(-1, 2)
        values = np.asarray(values)
        if values.shape != (self.capture.n_lights, len(pixels), 3):
            raise RegistrationError(f"dot-free patch {expression}/{camera}: values {values.shape} do not match "
                                    f"{self.capture.n_lights} lights x {len(pixels)} pixels")
        if not np.isfinite(values).all():
            raise RegistrationError(f"dot-free patch {expression}/{camera}: non-finite values")
        _save_npz_atomic(self.root / "dotfree" / expression / f"{camera}.npz", pixels=pixels,
                         values=values.astype(np.float16))

    def set_meta(self, key: str, value) -> None:
        self.meta[key] = value
        write_json_atomic(self.root / "registration.json", self.meta)
