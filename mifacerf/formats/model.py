"""The relightable morphable model on disk: geometry, blending structures, reflectance fields.

Layout::

    MODEL/
      model.json                 format, version, lights, cameras, expressions, template, references
      geometry.npz               vertices (S, T, 3), visible (S, C, T), status (S, T), triangles (F, 3),
                                 eye_centres (S, 2, 3), teeth (S, 2, 4, 4), head_pose (S, 4, 4)
      blend.npz                  the §5 blend model (mifacerf.blending.BlendModel)
      fields/<expr>/<cam>.texels.npz   texel map: pixels (N, 2) (row, col), tri (N,), bary (N, 3), depth (N,)
      fields/<expr>/<cam>.rf.npy       reflectance functions (N, L, 3) float16, texel-major

A field stores only the N pixels of camera ``cam`` where the template mesh of
expression ``expr`` is seen (ray cast through the pixel centres): per pixel its
triangle, barycentric coordinates and distance, and its reflectance function —
the dot-free, calibrated radiance per unit irradiance for every light, stored
texel-major so one texel's L×3 values are contiguous. Values are float16
(radiance per unit irradiance of skin is ≲ 1; float16 keeps 3 significant digits
and values up to 65504).

Opening a model reads ``model.json`` and ``geometry.npz`` only; a field's files are
read (memory-mapped) the first time a render needs that (expression, camera).

This module is the format: :class:`ModelFolder` reads it, :class:`ModelWriter` writes
it. :class:`mifacerf.rendering.model.Model` is the reader with the rendering-side
conveniences (the blend model, compressed fields, the spread visibility).
"""
from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from .files import read_json_manifest, write_json_atomic

FORMAT = "mifacerf.model"
VERSION = 1


class ModelError(ValueError):
    """A missing or inconsistent model folder; the message names the file."""


@dataclass
class Field:
    """One (expression, camera) reflectance field, restricted to the pixels where the template is seen.

    ``pixels`` (N, 2) int (row, col); ``tri`` (N,) int; ``bary`` (N, 3); ``depth`` (N,)
    distance from the camera centre (m); ``rf`` (N, L, 3) float16 (memory-mapped);
    ``shape`` (H, W) of the camera image.
    """

    expression: str
    camera: str
    pixels: np.ndarray
    tri: np.ndarray
    bary: np.ndarray
    depth: np.ndarray
    rf: np.ndarray
    shape: tuple[int, int]

    def __len__(self) -> int:
        return len(self.pixels)

    def depth_map(self) -> np.ndarray:
        """(H, W) distance of the seen template surface; +inf where it is not seen."""
        d = np.full(self.shape, np.inf, np.float32)
        d[self.pixels[:, 0], self.pixels[:, 1]] = self.depth
        return d

    @property
    def nbytes(self) -> int:
        return int(self.rf.size * self.rf.itemsize)


def _nbytes(entry) -> int:
    if isinstance(entry, Field):
        return entry.nbytes
    return int(sum(np.asarray(v).nbytes for v in entry.values() if hasattr(v, "nbytes")))


class ModelFolder:
    """A model folder opened for reading. Fields load lazily (an LRU of ``cache_bytes``)."""

    def __init__(self, root: str | os.PathLike, cache_bytes: int = 4 << 30):
        self.root = Path(root)
        self.meta = read_json_manifest(self.root / "model.json", FORMAT, VERSION, ModelError,
                                       "missing; build a model with 'mifacerf build CAPTURE -o MODEL'",
                                       "mifacerf model")
        self.cameras = [Camera.from_dict(c) for c in self.meta["cameras"]]
        self.light_directions = np.asarray(self.meta["lights"]["directions"], np.float64)
        self.solid_angles = np.asarray(self.meta["lights"]["solid_angles"], np.float64)
        self.expressions = [e["name"] for e in self.meta["expressions"]]
        self.categories = {e["name"]: e.get("category", "other") for e in self.meta["expressions"]}
        gpath = self.root / "geometry.npz"
        if not gpath.exists():
            raise ModelError(f"{gpath}: missing")
        g = np.load(gpath)
        try:
            self.vertices = g["vertices"]
            self.visible = g["visible"].astype(bool)
            self.status = g["status"]
            self.triangles = g["triangles"].astype(np.int64)
            self.eye_centres = g["eye_centres"]
            self.teeth = g["teeth"]
            self.head_pose = g["head_pose"]
        except KeyError as exc:
            raise ModelError(f"{gpath}: lacks {exc}") from exc
        s, t = self.vertices.shape[:2]
        if s != len(self.expressions) or self.visible.shape != (s, len(self.cameras), t):
            raise ModelError(f"{gpath}: shapes do not match model.json ({s} expressions, {len(self.cameras)} "
                             f"cameras, {t} vertices)")
        self.template = self.meta.get("template", {})
        self.neutral = self.meta.get("neutral", self.expressions[0])
        self.cache_bytes = cache_bytes
        self._fields: OrderedDict = OrderedDict()
        self.loaded_fields: list[tuple[str, str]] = []  # every (expression, camera) read from disk, in order

    # ---------------------------------------------------------------- access
    @property
    def n_lights(self) -> int:
        return len(self.light_directions)

    @property
    def n_vertices(self) -> int:
        return self.vertices.shape[1]

    def expression_index(self, name: str) -> int:
        try:
            return self.expressions.index(name)
        except ValueError:
            raise KeyError(f"model has no expression {name!r} (has {', '.join(self.expressions)})") from None

    def camera_index(self, name: str) -> int:
        for i, c in enumerate(self.cameras):
            if c.name == name:
                return i
        raise KeyError(f"model has no camera {name!r}")

    def has_field(self, s: int, c: int) -> bool:
        info = self.meta["fields"].get(f"{self.expressions[s]}/{self.cameras[c].name}")
        return bool(info and info["texels"] > 0)

    def field(self, s: int, c: int) -> Field:
        """The (expression index, camera index) field, loaded on first use (LRU-cached)."""
        key = (s, c)
        if key in self._fields:
            self._fields.move_to_end(key)
            return self._fields[key]
        e, cam = self.expressions[s], self.cameras[c]
        base = self.root / "fields" / e / cam.name
        tpath, rpath = base.with_suffix(".texels.npz"), base.with_suffix(".rf.npy")
        for p in (tpath, rpath):
            if not p.exists():
                raise ModelError(f"{p}: missing field file for expression {e!r}, camera {cam.name!r}")
        try:
            z = np.load(tpath)
            rf = np.load(rpath, mmap_mode="r")
            f = Field(e, cam.name, z["pixels"].astype(np.int64), z["tri"].astype(np.int64), z["bary"],
                      z["depth"], rf, (cam.height, cam.width))
        except (KeyError, ValueError, OSError, EOFError) as exc:
            raise ModelError(f"{base}: unreadable field ({exc})") from exc
        if rf.shape != (len(f.pixels), self.n_lights, 3):
            raise ModelError(f"{rpath}: shape {rf.shape}, expected ({len(f.pixels)}, {self.n_lights}, 3)")
        self.loaded_fields.append((e, cam.name))
        self._fields[key] = f
        total = sum(_nbytes(x) for x in self._fields.values())
        while total > self.cache_bytes and len(self._fields) > 1:
            _, old = self._fields.popitem(last=False)
            total -= _nbytes(old)
        return f

    def part_field(self, reference: str, c: int) -> dict | None:
        """Eye/teeth texels of a reference expression in camera ``c``: {pixels (N, 2), part (N,) index into
        :data:`.parts.PARTS`, depth (N,), rf (N, L, 3) float16}, or None if the model has none."""
        key = ("parts", reference, c)
        if key in self._fields:
            return self._fields[key]
        base = self.root / "fields" / reference / self.cameras[c].name
        tpath, rpath = base.with_suffix(".parts.npz"), base.with_suffix(".parts.rf.npy")
        if not tpath.exists():
            return None
        if not rpath.exists():
            raise ModelError(f"{rpath}: missing (its texel map {tpath.name} exists)")
        z = np.load(tpath)
        out = {"pixels": z["pixels"].astype(np.int64), "part": z["part"].astype(np.int64), "depth": z["depth"],
               "rf": np.load(rpath, mmap_mode="r")}
        self.loaded_fields.append((reference, self.cameras[c].name + ":parts"))
        self._fields[key] = out
        return out

    @property
    def references(self) -> dict:
        """{"eyes" / "teeth" / "mouth": expression}: the parts' reference expressions."""
        return dict(self.meta.get("references", {}))

    @property
    def part_sources(self) -> dict:
        """{group: [expressions whose part fields are stored]} (older models: the references only)."""
        stored = self.meta.get("part_sources") or {g: [r] for g, r in self.references.items()}
        return {g: list(v) for g, v in stored.items()}

    def size_on_disk(self) -> int:
        return sum(p.stat().st_size for p in self.root.rglob("*") if p.is_file())


class ModelWriter:
    """Writes a model folder; ``model.json`` last."""

    def __init__(self, root: str | os.PathLike, light_directions, solid_angles, cameras: list[Camera],
                 expressions: list[tuple[str, str]], triangles, template: dict | None = None,
                 neutral: str | None = None, overwrite: bool = False):
        self.root = Path(root)
        if (self.root / "model.json").exists() and not overwrite:
            raise ModelError(f"{self.root}: already holds a model; choose another folder or overwrite")
        self.root.mkdir(parents=True, exist_ok=True)
        if (self.root / "model.json").exists():
            (self.root / "model.json").unlink()
        self.light_directions = np.asarray(light_directions, np.float64)
        self.solid_angles = np.asarray(solid_angles, np.float64)
        self.cameras = cameras
        self.expressions = expressions
        self.triangles = np.asarray(triangles, np.int64)
        self.template = template or {}
        self.neutral = neutral or expressions[0][0]
        self.fields: dict[str, dict] = {}
        self.geometry: dict[str, list] = {k: [] for k in ("vertices", "visible", "status", "eye_centres", "teeth",
                                                           "head_pose")}
        self.extra: dict = {}

    def add_geometry(self, vertices, visible, status, eye_centres, teeth, head_pose) -> None:
        for k, v in (("vertices", vertices), ("visible", visible), ("status", status),
                     ("eye_centres", eye_centres), ("teeth", teeth), ("head_pose", head_pose)):
            self.geometry[k].append(np.asarray(v))

    def write_field(self, expression: str, camera: Camera, pixels, tri, bary, depth, rf) -> None:
        """One field: texel map arrays (N, ...) and reflectance functions (N, L, 3)."""
        rf = np.asarray(rf)
        n = len(pixels)
        if rf.shape != (n, len(self.light_directions), 3):
            raise ModelError(f"field {expression}/{camera.name}: rf shape {rf.shape}, expected "
                             f"({n}, {len(self.light_directions)}, 3)")
        if not np.isfinite(rf).all():
            raise ModelError(f"field {expression}/{camera.name}: non-finite reflectance values")
        if np.abs(rf).max(initial=0) > 65504:
            raise ModelError(f"field {expression}/{camera.name}: values overflow float16")
        base = self.root / "fields" / expression / camera.name
        base.parent.mkdir(parents=True, exist_ok=True)
        tmp = base.with_name(f".{camera.name}.tmp.npz")
        np.savez_compressed(tmp, pixels=np.asarray(pixels, np.int16 if max(camera.width, camera.height) < 32767
                                                   else np.int32),
                            tri=np.asarray(tri, np.int32), bary=np.asarray(bary, np.float32),
                            depth=np.asarray(depth, np.float32))
        os.replace(tmp, base.with_suffix(".texels.npz"))
        tmp = base.with_name(f".{camera.name}.tmp.npy")
        np.save(tmp, rf.astype(np.float16))
        os.replace(tmp, base.with_suffix(".rf.npy"))
        self.fields[f"{expression}/{camera.name}"] = {"texels": int(n)}

    def finish(self, blend=None) -> Path:
        g = {k: np.stack(v) for k, v in self.geometry.items()}
        g["triangles"] = self.triangles
        tmp = self.root / ".geometry.tmp.npz"
        np.savez_compressed(tmp, **g)
        os.replace(tmp, self.root / "geometry.npz")
        if blend is not None:
            blend.save(self.root / "blend.npz")
        meta = {
            "format": FORMAT, "version": VERSION,
            "units": "metres; reflectance functions: linear sRGB radiance per unit irradiance",
            "lights": {"directions": self.light_directions.tolist(), "solid_angles": self.solid_angles.tolist()},
            "cameras": [c.to_dict() for c in self.cameras],
            "expressions": [{"name": n, "category": c} for n, c in self.expressions],
            "neutral": self.neutral,
            "template": self.template,
            "fields": self.fields,
            **self.extra,
        }
        write_json_atomic(self.root / "model.json", meta)
        return self.root / "model.json"
