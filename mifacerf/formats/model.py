"""The relightable morphable model on disk: geometry, blending structures, reflectance fields.

Layout::

    MODEL/
      model.json                 format, version, lights, cameras, expressions, template, references,
                                 fields, and ``files``: size and sha256 of every other file (written last)
      geometry.npz               vertices (S, T, 3), visible (S, C, T), status (S, T), triangles (F, 3),
                                 eye_centres (S, 2, 3), teeth (S, 2, 4, 4), head_pose (S, 4, 4)
      blend.npz                  the §5 blend model (mifacerf.blending.BlendModel)
      fields/<expr>/<cam>.texels.npz   texel map: pixels (N, 2) (row, col), tri (N,), bary (N, 3), depth (N,)
      fields/<expr>/<cam>.rf.npy       reflectance functions (N, L, 3) float16, texel-major
      fields/<ref>/<cam>.parts.npz     eye / teeth / mouth texels of a part source (pixels, part, depth)
      fields/<ref>/<cam>.parts.rf.npy  their reflectance functions (N, L, 3) float16
      fields/<expr>/<cam>.<method><rank>.npz   compressed fields (mifacerf compress), listed in "compressed"

A field stores only the N pixels of camera ``cam`` where the template mesh of
expression ``expr`` is seen (ray cast through the pixel centres): per pixel its
triangle, barycentric coordinates and distance, and its reflectance function —
the dot-free, calibrated radiance per unit irradiance for every light, stored
texel-major so one texel's L×3 values are contiguous. Values are float16
(radiance per unit irradiance of skin is ≲ 1; float16 keeps 3 significant digits
and values up to 65504).

Opening a model reads ``model.json`` and ``geometry.npz`` only; a field's files are
read (memory-mapped) the first time a render needs that (expression, camera).

Integrity (version 2): ``model.json["files"]`` lists ``{"size", "sha256"}`` of every
file of the folder. Opening checks that every listed file exists with its size
(one ``stat`` each) and the checksum of ``geometry.npz``; a field's, a part field's,
a compressed field's and the blend model's files are checksummed the first time they
are read (a field's ``.rf.npy`` when it is first memory-mapped: once per file and
process; a file already checked by an earlier process, and unchanged since, is trusted from its stamp:
:func:`.files.check_entry`); :meth:`ModelFolder.verify` (``mifacerf verify MODEL``) checks everything at
once. Every mismatch raises :class:`ModelError` naming the file. Version-1 models
(no ``files``) are still read, unchecked.

Transactions: :class:`ModelWriter` writes into a sibling folder ``.<name>.building-*``
and swaps it in when complete (:func:`.files.swap_in`), holding the folder's lock
(:class:`.files.FolderLock`) all along; a failed or killed build leaves the previous
model as it was, and a build interrupted during the swap is finished by the next
open or build (:func:`.files.repair_swap`). ``--overwrite`` replaces the whole model
(compressed fields included: they belong to the old fields) only once the new one is
complete. Files added to a finished model (``mifacerf compress``) are a transaction too
(:func:`update_model`): a hard-linked copy of the folder gets the new files and
``model.json``, and is swapped in the same way.

This module is the format: :class:`ModelFolder` reads it, :class:`ModelWriter` writes
it. :class:`mifacerf.rendering.model.Model` is the reader with the rendering-side
conveniences (the blend model, compressed fields, the spread visibility).
"""
from __future__ import annotations

import os
from collections import OrderedDict
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..errors import MifacerfError
from .files import (FolderLock, check_entry, file_entry, link_tree, new_building_dir, read_json_manifest,
                    repair_if_needed, repair_swap, require_keys, save_npy_atomic, save_npz_atomic, swap_in,
                    verify_entries, write_json_atomic)

FORMAT = "mifacerf.model"
VERSION = 2
READS = (1, 2)       #: versions this reader opens (1: before the checksums)
MARKER = "model.json"
#: keys model.json must hold (version 1 lacks the last three)
REQUIRED = ("lights", "cameras", "expressions", "neutral", "template", "fields", "files", "references",
            "part_sources")


class ModelError(MifacerfError, ValueError):
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
        repair_if_needed(self.root, MARKER, ModelError)
        mpath = self.root / MARKER
        self.meta = read_json_manifest(mpath, FORMAT, READS, ModelError,
                                       "missing; build a model with 'mifacerf build CAPTURE -o MODEL'",
                                       "mifacerf model")
        m = self.meta
        require_keys(m, REQUIRED if m["version"] >= 2 else REQUIRED[:-3], str(mpath), ModelError)
        require_keys(m["lights"], ("directions", "solid_angles"), f"{mpath}: lights", ModelError)
        for e in m["expressions"]:
            require_keys(e, ("name", "category"), f"{mpath}: an expression entry", ModelError)
        #: {relative path: {"size", "sha256"}} (None: a version-1 model, unchecked)
        self.files: dict | None = m.get("files")
        self._verified: set[str] = set()
        if self.files is not None:
            for rel, entry in self.files.items():
                check_entry(self.root / rel, entry, ModelError, checksum=False)
        try:
            self.cameras = [Camera.from_dict(c) for c in m["cameras"]]
        except (KeyError, ValueError, TypeError) as exc:
            raise ModelError(f"{mpath}: invalid camera entry ({exc})") from exc
        self.light_directions = np.asarray(m["lights"]["directions"], np.float64)
        self.solid_angles = np.asarray(m["lights"]["solid_angles"], np.float64)
        self.expressions = [e["name"] for e in m["expressions"]]
        self.categories = {e["name"]: e["category"] for e in m["expressions"]}
        gpath = self.root / "geometry.npz"
        if not gpath.exists():
            raise ModelError(f"{gpath}: missing")
        self.check_file(gpath)
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
        self.template = m["template"]
        self.neutral = m["neutral"]
        if self.neutral not in self.expressions:
            raise ModelError(f"{mpath}: neutral {self.neutral!r} is not one of its expressions")
        self.cache_bytes = cache_bytes
        self._fields: OrderedDict = OrderedDict()
        self.loaded_fields: list[tuple[str, str]] = []  # every (expression, camera) read from disk, in order

    # ---------------------------------------------------------------- integrity
    def check_file(self, path: Path, required: bool = True) -> None:
        """Checksum ``path`` against the manifest, once per process and file (no-op for version 1);
        ``required``: a file the manifest does not list is an error (else it is ignored)."""
        if self.files is None:
            return
        rel = Path(path).relative_to(self.root).as_posix()
        if rel in self._verified:
            return
        entry = self.files.get(rel)
        if entry is None:
            if required:
                raise ModelError(f"{path}: not in the model's manifest (model.json 'files'); the folder was "
                                 "changed after it was built")
            return
        check_entry(Path(path), entry, ModelError)
        self._verified.add(rel)

    def verify(self) -> list[str]:
        """Every problem found by checking each listed file's size and checksum (empty: all verify)."""
        if self.files is None:
            return [f"{self.root / MARKER}: a version-1 model without checksums; rebuild it to get them"]
        return verify_entries(self.root, self.files, ModelError)

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
            self.check_file(p)
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
        self.check_file(tpath)
        self.check_file(rpath)
        z = np.load(tpath)
        out = {"pixels": z["pixels"].astype(np.int64), "part": z["part"].astype(np.int64), "depth": z["depth"],
               "rf": np.load(rpath, mmap_mode="r")}
        self.loaded_fields.append((reference, self.cameras[c].name + ":parts"))
        self._fields[key] = out
        return out

    @property
    def references(self) -> dict:
        """{"eyes" / "teeth" / "mouth": expression}: the parts' reference expressions."""
        return dict(self.meta.get("references", {}))      # (version 1 without parts: none)

    @property
    def part_sources(self) -> dict:
        """{group: [expressions whose part fields are stored]} (older models: the references only)."""
        stored = self.meta.get("part_sources") or {g: [r] for g, r in self.references.items()}
        return {g: list(v) for g, v in stored.items()}

    @property
    def surface(self) -> dict:
        """{"method": "phong" / "flat", "curved": n}: the surface the registration fitted the outlines against,
        which renders trace (Phong level ``n``; 1: flat triangles). Models without it (built before the entry):
        flat."""
        from ..geometry.boubekeur2008 import surface_entry

        return dict(self.meta.get("surface") or surface_entry(1))

    def size_on_disk(self) -> int:
        return sum(p.stat().st_size for p in self.root.rglob("*") if p.is_file())


class ModelWriter:
    """Writes a model folder as one transaction: into ``.<name>.building-*`` beside it, ``model.json``
    (with every other file's size and sha256) last, then swapped in by :meth:`finish`; :meth:`abort`
    (or a failure inside ``with ModelWriter(...) as w:``) leaves the previous model untouched. The
    folder's lock is held from construction to finish / abort (``wait``: see :class:`.files.FolderLock`).

    ``root`` is the folder being written (the building folder); ``target`` the model folder.
    """

    def __init__(self, root: str | os.PathLike, light_directions, solid_angles, cameras: list[Camera],
                 expressions: list[tuple[str, str]], triangles, template: dict | None = None,
                 neutral: str | None = None, overwrite: bool = False, wait: bool | float = True, log=None):
        self.target = Path(root)
        self._lock = FolderLock(self.target, ModelError, wait=wait, log=log or _stderr, what="model build")
        self._lock.acquire()
        try:
            repair_swap(self.target, MARKER)
            if (self.target / MARKER).exists() and not overwrite:
                raise ModelError(f"{self.target}: already holds a model; choose another folder or overwrite")
            if self.target.exists() and not self.target.is_dir():
                raise ModelError(f"{self.target}: not a folder")
            if self.target.is_dir() and not (self.target / MARKER).exists() and any(self.target.iterdir()):
                raise ModelError(f"{self.target}: holds files but no model.json, so it is not a model folder; "
                                 "refusing to replace it (choose a new or empty folder)")
            self.root = new_building_dir(self.target)
        except BaseException:
            self._lock.release()
            raise
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

    def __enter__(self) -> "ModelWriter":
        return self

    def __exit__(self, exc_type, *exc) -> None:
        if exc_type is not None:
            self.abort()

    def abort(self) -> None:
        """Discard what was written (the previous model stays) and release the lock."""
        import shutil

        if self._lock is None:
            return
        shutil.rmtree(self.root, ignore_errors=True)
        self._lock.release()
        self._lock = None

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
        save_npz_atomic(base.with_suffix(".texels.npz"),
                        pixels=np.asarray(pixels, np.int16 if max(camera.width, camera.height) < 32767 else np.int32),
                        tri=np.asarray(tri, np.int32), bary=np.asarray(bary, np.float32),
                        depth=np.asarray(depth, np.float32))
        save_npy_atomic(base.with_suffix(".rf.npy"), rf.astype(np.float16))
        self.fields[f"{expression}/{camera.name}"] = {"texels": int(n)}

    def finish(self, blend=None) -> Path:
        """Write the geometry, the blend model and ``model.json`` (with the checksums), then swap the
        folder in; returns ``target/model.json``."""
        if self._lock is None:
            raise ModelError(f"{self.target}: this writer was already finished or aborted")
        try:
            g = {k: np.stack(v) for k, v in self.geometry.items()}
            g["triangles"] = self.triangles
            save_npz_atomic(self.root / "geometry.npz", **g)
            if blend is not None:
                blend.save(self.root / "blend.npz")
            meta = {
                "format": FORMAT, "version": VERSION,
                "units": "metres; reflectance functions: linear sRGB radiance per unit irradiance",
                "lights": {"directions": self.light_directions.tolist(),
                           "solid_angles": self.solid_angles.tolist()},
                "cameras": [c.to_dict() for c in self.cameras],
                "expressions": [{"name": n, "category": c} for n, c in self.expressions],
                "neutral": self.neutral,
                "template": self.template,
                "fields": self.fields,
                "references": {}, "part_sources": {},
                **self.extra,
            }
            meta["files"] = {p.relative_to(self.root).as_posix(): file_entry(p)
                             for p in sorted(self.root.rglob("*")) if p.is_file() and p.name != MARKER}
            write_json_atomic(self.root / MARKER, meta)
            swap_in(self.target, self.root, MARKER)
        except BaseException:
            self.abort()
            raise
        self._lock.release()
        self._lock = None
        return self.target / MARKER


class ModelUpdate:
    """Files being added to a finished model (:func:`update_model`): write them under :attr:`root` (a
    hard-linked copy of the model) and :meth:`add` each; :meth:`update` changes ``model.json``."""

    def __init__(self, root: Path, meta: dict):
        self.root, self.meta, self.written = root, meta, []
        self._updates = []

    def add(self, path) -> None:
        self.written.append(Path(path))

    def update(self, fn) -> None:
        """``fn(meta)`` is applied to ``model.json`` (as it is on disk, under the lock) at the commit."""
        self._updates.append(fn)


@contextmanager
def update_model(model: ModelFolder, what: str = "model update", log=None):
    """``with update_model(model) as u:`` add files to a finished model as one transaction (compressed
    fields): under the model's lock, ``u.root`` is a new folder beside the model holding hard links to
    every file of it; the block writes the new files there (``u.add(path)``; a file replaced is
    written by rename, so the old model's file is untouched), then ``model.json`` with their sizes and
    checksums is written and the folder swapped in (:func:`.files.swap_in`). A failure or a kill at any
    moment leaves the model as it was, or (once swapped) the new files all listed and complete; a model
    being read keeps its files (the same inodes). ``model`` (``meta``, ``files``) follows the update."""
    import shutil

    target = Path(model.root)
    with FolderLock(target, ModelError, what=what, log=log or _stderr):
        repair_swap(target, MARKER)
        meta = read_json_manifest(target / MARKER, FORMAT, READS, ModelError, "missing", "mifacerf model")
        building = new_building_dir(target)
        try:
            link_tree(target, building)
            u = ModelUpdate(building, meta)
            yield u
            for fn in u._updates:
                fn(meta)
            if meta.get("files") is not None:
                for p in u.written:
                    meta["files"][Path(p).relative_to(building).as_posix()] = file_entry(p)
            (building / MARKER).unlink()               # (a link to the old one: written anew, not through it)
            write_json_atomic(building / MARKER, meta)
            swap_in(target, building, MARKER)
        except BaseException:
            shutil.rmtree(building, ignore_errors=True)
            raise
    model.meta = meta
    model.files = meta.get("files")
    for p in u.written:
        model._verified.discard(Path(p).relative_to(building).as_posix())


def record_files(model: ModelFolder, paths, update=None) -> dict:
    """Add files already written into a finished model to its manifest and apply ``update(meta)`` to its
    ``model.json`` as it is on disk, under the model's lock (no lost update); returns (and sets)
    ``model.meta``. Not a transaction (a kill between a file's write and this leaves it unlisted, or a
    listed file rewritten): writers use :func:`update_model`."""
    root = Path(model.root)
    with FolderLock(root, ModelError, what="model update"):
        meta = read_json_manifest(root / MARKER, FORMAT, READS, ModelError, "missing", "mifacerf model")
        if update is not None:
            update(meta)
        if meta.get("files") is not None:
            for p in paths:
                meta["files"][Path(p).relative_to(root).as_posix()] = file_entry(p)
        write_json_atomic(root / MARKER, meta)
    model.meta = meta
    model.files = meta.get("files")
    for p in paths:
        model._verified.discard(Path(p).relative_to(root).as_posix())
    return meta


def _stderr(message: str) -> None:
    import sys

    print(message, file=sys.stderr)
