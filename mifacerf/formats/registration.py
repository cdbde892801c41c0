"""The registration folder: registration's output, the model build's input.

Layout (default ``CAPTURE/registration/``)::

    registration.json                  format, version, the capture it belongs to, per-expression report,
                                       ``files``: size and sha256 of every other file (rewritten last)
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

Integrity (version 2): ``registration.json["files"]`` lists ``{"size", "sha256"}`` of
every file of the folder. Opening checks that each listed file exists with its size
and the template's checksum; an expression's ``.npz`` and a dot-free patch are
checksummed when first read; :meth:`Registration.verify` (``mifacerf verify``) checks
everything. A mismatch raises :class:`RegistrationError` naming the file. A dot-free
patch the manifest does not list does not belong to the registration and is not
read. Version-1 folders (no ``files``) are read unchecked and upgraded by the next
``register``.

Transactions (:class:`RegistrationWriter`): one writer at a time, serialised by the
folder's lock (:class:`.files.FolderLock`: a second ``register`` waits, saying who holds
it; a killed holder's lock is free at once). Each expression is one commit: its
``.npz`` and dot-free patches are written into ``.staging-*/``, then an intent
``.commit.json`` (the files to move and delete, the new ``registration.json``) is
written atomically — the commit point — and applied: files moved into place, the
expression's old files that the new ones do not replace deleted, ``registration.json``
rewritten, intent removed. Killed before the intent, the folder is as before; after,
the next reader or writer finishes the commit. Re-registering an expression replaces
it and nothing else. A full re-registration (``register --force`` without
``--expressions``) writes a new folder beside the old one and swaps it in when
complete (:func:`.files.swap_in`).
"""
from __future__ import annotations

import copy
import json
import os
import shutil
import sys
import tempfile
import time
import weakref
from pathlib import Path

import numpy as np

from .capture import Capture
from ..errors import MifacerfError
from .files import (FolderLock, check_entry, file_entry, fsync_dir, new_building_dir, read_json,
                    read_json_manifest, repair_if_needed, repair_swap, require_keys, save_npz_atomic, swap_in,
                    verify_entries, write_json_atomic)

FORMAT = "mifacerf.registration"
VERSION = 2
READS = (1, 2)                 #: versions this reader opens (1: before the checksums)
MARKER = "registration.json"
INTENT = ".commit.json"
STAGING = ".staging-"
#: keys registration.json must hold (version 1 lacks "files")
REQUIRED = ("capture", "expressions", "files")


class RegistrationError(MifacerfError, ValueError):
    """A missing or inconsistent registration folder; the message names the file."""


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
        save_npz_atomic(path, vertices=self.vertices, status=self.status, uv=self.uv, visible=self.visible,
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


def expression_rel(name: str) -> str:
    return f"expressions/{name}.npz"


def dotfree_rel(expression: str, camera: str) -> str:
    return f"dotfree/{expression}/{camera}.npz"


# ---------------------------------------------------------------- commits
def _apply_intent(root: Path, intent: dict) -> None:
    """Finish a commit whose intent is on disk (idempotent: a re-run after a kill completes it)."""
    staging = root / intent["staging"]
    for rel in intent["moves"]:
        src, dst = staging / rel, root / rel
        if src.exists():
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.replace(src, dst)
            fsync_dir(dst.parent)
    for rel in intent["delete"]:
        try:
            (root / rel).unlink()
        except FileNotFoundError:
            pass
    write_json_atomic(root / MARKER, intent["meta"])
    (root / INTENT).unlink(missing_ok=True)
    shutil.rmtree(staging, ignore_errors=True)


def _stale_staging(root: Path) -> list[Path]:
    try:
        return [root / n for n in os.listdir(root) if n.startswith(STAGING)]
    except OSError:
        return []


def recover(root: str | os.PathLike) -> None:
    """Finish an interrupted commit and delete uncommitted staging folders (the caller holds the lock)."""
    root = Path(root)
    ipath = root / INTENT
    if ipath.exists():
        intent = read_json(ipath, RegistrationError, "missing")
        _apply_intent(root, intent)
    for p in _stale_staging(root):
        shutil.rmtree(p, ignore_errors=True)


def _recover_for_reading(root: Path, settle_s: float = 10.0) -> None:
    """A reader that finds an interrupted commit (or a killed writer's staging) finishes it (drops it) when
    no writer holds the lock, else waits for the writer to finish the commit."""
    if not (root / INTENT).exists() and not _stale_staging(root):
        return
    try:
        with FolderLock(root, RegistrationError, wait=False):
            recover(root)
        return
    except RegistrationError:
        if not (root / INTENT).exists():
            return                        # a writer at work: its staging is its own
    except OSError:
        raise RegistrationError(f"{root / INTENT}: an interrupted commit that cannot be finished here (read-only?); "
                                "run 'mifacerf register' on the capture to finish it") from None
    deadline = time.monotonic() + settle_s
    while (root / INTENT).exists() and time.monotonic() < deadline:
        time.sleep(0.05)


def _read_meta(root: Path) -> dict:
    mpath = root / MARKER
    meta = read_json_manifest(mpath, FORMAT, READS, RegistrationError, "missing; run 'mifacerf register' first",
                              "mifacerf registration")
    require_keys(meta, REQUIRED if meta["version"] >= 2 else REQUIRED[:-1], str(mpath), RegistrationError)
    if not isinstance(meta["expressions"], dict):
        raise RegistrationError(f"{mpath}: 'expressions' must be an object {{name: report}}")
    if meta["version"] >= 2:
        for name in meta["expressions"]:
            if expression_rel(name) not in meta["files"]:
                raise RegistrationError(f"{mpath}: expression {name!r} has no entry for {expression_rel(name)} "
                                        "in 'files'")
    return meta


class Registration:
    """A registration folder opened for reading (lazy: expressions and patches load on demand)."""

    def __init__(self, root: str | os.PathLike, capture: Capture | None = None):
        self.root = Path(root)
        repair_if_needed(self.root, MARKER, RegistrationError)
        _recover_for_reading(self.root)
        self.meta = _read_meta(self.root)
        #: {relative path: {"size", "sha256"}} (None: a version-1 folder, unchecked)
        self.files: dict | None = self.meta.get("files")
        self._verified: set[str] = set()
        if self.files is not None:
            for rel, entry in self.files.items():
                check_entry(self.root / rel, entry, RegistrationError, checksum=False)
        tpath = self.root / "template.json"
        if not tpath.exists():
            raise RegistrationError(f"{tpath}: missing")
        self.check_file(tpath)
        self.template = read_json(tpath, RegistrationError, "missing")
        self.capture = capture if capture is not None else Capture(self._capture_path())
        self._cache: dict[str, RegisteredExpression] = {}

    def _capture_path(self) -> Path:
        p = Path(self.meta["capture"])
        return p if p.is_absolute() else (self.root / p).resolve()

    def check_file(self, path: Path) -> bool:
        """Checksum ``path`` against the manifest once per process (True); False when the manifest does
        not list it; no-op (True) for version 1."""
        if self.files is None:
            return True
        rel = Path(path).relative_to(self.root).as_posix()
        if rel in self._verified:
            return True
        entry = self.files.get(rel)
        if entry is None:
            return False
        check_entry(Path(path), entry, RegistrationError)
        self._verified.add(rel)
        return True

    def check_template(self, names, arrays) -> dict:
        """The template's arrays (``arrays(template)``, e.g. :func:`mifacerf.rendering.build.template_arrays`),
        checked to be the one expressions ``names`` were registered on: ``template.json`` listed in the
        manifest (its checksum was verified at open), triangles indexing its vertices, and every expression
        with as many vertices as the template and one projection per capture camera. Otherwise
        :class:`RegistrationError` naming the file."""
        tpath = self.root / "template.json"
        if self.files is not None and "template.json" not in self.files:
            raise RegistrationError(f"{tpath}: not in the registration's manifest ({MARKER} 'files'): it was "
                                    "changed after registering; register again (mifacerf register --force)")
        try:
            t = arrays(self.template)
            n, tri = int(t["n_vertices"]), np.asarray(t["triangles"])
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            raise RegistrationError(f"{tpath}: not a usable template ({type(exc).__name__}: {exc})") from exc
        if tri.ndim != 2 or tri.shape[1:] != (3,) or not len(tri) or tri.min() < 0 or tri.max() >= n:
            raise RegistrationError(f"{tpath}: triangles of shape {tri.shape} do not index its {n} vertices")
        for name in names:
            r = self.expression(name)
            where = self.root / expression_rel(name)
            if len(r.vertices) != n:
                raise RegistrationError(f"{where}: {len(r.vertices)} vertices, but the registration's template "
                                        f"{tpath} has {n}: not registered on this template; register again "
                                        "(mifacerf register --force)")
            if len(r.uv) != len(self.capture.camera_names):
                raise RegistrationError(f"{where}: projections into {len(r.uv)} cameras, the capture has "
                                        f"{len(self.capture.camera_names)}")
        return t

    def verify(self) -> list[str]:
        """Every problem found by checking each listed file's size and checksum (empty: all verify)."""
        if self.files is None:
            return [f"{self.root / MARKER}: a version-1 registration without checksums; 'mifacerf register' "
                    "adds them"]
        return verify_entries(self.root, self.files, RegistrationError)

    @property
    def expression_names(self) -> list[str]:
        """Registered expressions, in capture order."""
        done = self.meta["expressions"]
        return [e for e in self.capture.expression_names if e in done]

    def report(self, name: str) -> dict:
        return self.meta["expressions"][name]

    def expression(self, name: str) -> RegisteredExpression:
        if name not in self._cache:
            path = self.root / expression_rel(name)
            if path.exists():
                self.check_file(path)
            self._cache[name] = RegisteredExpression.load(path, name)
        return self._cache[name]

    def dotfree_patch(self, expression: str, camera: str) -> tuple[np.ndarray, np.ndarray] | None:
        path = self.root / dotfree_rel(expression, camera)
        if not path.exists() or not self.check_file(path):
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


def _normalised(value):
    return json.loads(json.dumps(value))


def _stderr(message: str) -> None:
    print(message, file=sys.stderr)


class RegistrationWriter:
    """Writes a registration folder, one committed expression at a time (see the module docstring).

    Holds the folder's lock from construction to :meth:`finish` / :meth:`abort` (or until the writer
    is garbage-collected); ``wait``: see :class:`.files.FolderLock`. ``fresh``: start a new folder
    beside ``root`` that :meth:`finish` swaps in (the old one stays until then). ``root`` is the
    folder being written; ``target`` the registration folder.
    """

    def __init__(self, root: str | os.PathLike, capture: Capture, template: dict, fresh: bool = False,
                 wait: bool | float = True, log=None):
        self.target = Path(root)
        self.capture = capture
        self.fresh = fresh
        lock = FolderLock(self.target, RegistrationError, wait=wait, log=log or _stderr, what="registration")
        lock.acquire()
        self._lock = lock
        self._release = weakref.finalize(self, lock.release)
        try:
            repair_swap(self.target, MARKER)
            if fresh:
                self.root = new_building_dir(self.target)
            else:
                self.root = self.target
                self.root.mkdir(parents=True, exist_ok=True)
                recover(self.root)
            self._open(template)
        except BaseException:
            self.abort()
            raise
        self._staging: Path | None = None
        self._staged: dict[str, list[str]] = {}

    def _open(self, template: dict) -> None:
        path = self.root / MARKER
        changed = False
        if path.exists():
            self.meta = _read_meta(self.root)
            if self.meta["version"] < 2:         # upgrade: checksum what is there
                self.meta["version"] = VERSION
                files = {}
                for name in self.meta["expressions"]:
                    for p in [self.root / expression_rel(name),
                              *sorted((self.root / "dotfree" / name).glob("*.npz"))]:
                        if p.exists():
                            files[p.relative_to(self.root).as_posix()] = file_entry(p)
                self.meta["files"] = files
                self.meta["expressions"] = {n: r for n, r in self.meta["expressions"].items()
                                            if expression_rel(n) in files}
                changed = True
        else:
            rel = os.path.relpath(self.capture.root.resolve(), self.target.resolve())
            self.meta = {"format": FORMAT, "version": VERSION, "capture": rel, "expressions": {}, "files": {}}
            changed = True
        tpath = self.root / "template.json"
        old = None
        if tpath.exists():
            try:
                old = json.loads(tpath.read_text())
            except (json.JSONDecodeError, UnicodeDecodeError):
                old = None
        if old != _normalised(template) or "template.json" not in self.meta["files"]:
            if old != _normalised(template):
                write_json_atomic(tpath, template)
            self.meta["files"]["template.json"] = file_entry(tpath)
            changed = True
        if changed:
            write_json_atomic(path, self.meta)

    # ------------------------------------------------------------------ state
    def done(self, name: str) -> bool:
        return name in self.meta["expressions"] and (self.root / expression_rel(name)).exists()

    def load(self, name: str) -> RegisteredExpression:
        """A committed expression, checked against its checksum."""
        path = self.root / expression_rel(name)
        entry = self.meta.get("files", {}).get(expression_rel(name))
        if entry is not None:
            check_entry(path, entry, RegistrationError)
        return RegisteredExpression.load(path, name)

    def _stage(self) -> Path:
        if self._staging is None:
            self._staging = Path(tempfile.mkdtemp(prefix=f"{STAGING}{os.getpid()}-", dir=self.root))
        return self._staging

    def write_dotfree(self, expression: str, camera: str, pixels: np.ndarray, values: np.ndarray) -> None:
        """Stage one dot-free patch; it lands with its expression's :meth:`write_expression`."""
        pixels = np.asarray(pixels, np.int32).reshape(-1, 2)
        values = np.asarray(values)
        if values.shape != (self.capture.n_lights, len(pixels), 3):
            raise RegistrationError(f"dot-free patch {expression}/{camera}: values {values.shape} do not match "
                                    f"{self.capture.n_lights} lights x {len(pixels)} pixels")
        if not np.isfinite(values).all():
            raise RegistrationError(f"dot-free patch {expression}/{camera}: non-finite values")
        rel = dotfree_rel(expression, camera)
        save_npz_atomic(self._stage() / rel, pixels=pixels, values=values.astype(np.float16))
        staged = self._staged.setdefault(expression, [])
        if rel not in staged:
            staged.append(rel)

    def write_expression(self, reg: RegisteredExpression, report: dict, keep_dotfree: bool = False) -> None:
        """Commit one expression: its geometry, the dot-free patches staged for it, its report.

        The expression's dot-free patches become exactly those staged since its last commit, unless
        ``keep_dotfree`` (an update of the geometry alone keeps the committed patches)."""
        rel = expression_rel(reg.name)
        reg.save(self._stage() / rel)
        moves = [rel, *self._staged.pop(reg.name, [])]
        new = copy.deepcopy(self.meta)
        new["expressions"][reg.name] = _normalised(report)
        prefix = f"dotfree/{reg.name}/"
        dropped = [r for r in new["files"] if r == rel or (not keep_dotfree and r.startswith(prefix))]
        for r in dropped:
            del new["files"][r]
        for r in moves:
            new["files"][r] = file_entry(self._staging / r)
        delete = [r for r in dropped if r not in moves]
        if not keep_dotfree:           # unlisted leftovers of older versions too
            delete += [p.relative_to(self.root).as_posix() for p in sorted((self.root / prefix).glob("*.npz"))
                       if p.relative_to(self.root).as_posix() not in moves and
                       p.relative_to(self.root).as_posix() not in delete]
        intent = {"staging": self._staging.name, "moves": moves, "delete": delete, "meta": new}
        write_json_atomic(self.root / INTENT, intent)          # the commit point
        _apply_intent(self.root, intent)
        self._staging = None
        self.meta = new

    def set_meta(self, key: str, value) -> None:
        value = _normalised(value)
        if key in self.meta and self.meta[key] == value:
            return                     # unchanged: registration.json is not rewritten
        self.meta[key] = value
        write_json_atomic(self.root / MARKER, self.meta)

    # ------------------------------------------------------------------ end
    def finish(self) -> Path:
        """Swap a fresh folder in, drop uncommitted staging, release the lock; returns the folder."""
        if self._lock is None:
            return self.target
        try:
            if self._staging is not None:
                shutil.rmtree(self._staging, ignore_errors=True)
                self._staging = None
            if self.fresh:
                swap_in(self.target, self.root, MARKER)
                self.root = self.target
        except BaseException:
            self.abort()
            raise
        self._unlock()
        return self.target

    def abort(self) -> None:
        """Discard what was not committed (a fresh folder entirely) and release the lock."""
        if self._lock is None:
            return
        if getattr(self, "_staging", None) is not None:
            shutil.rmtree(self._staging, ignore_errors=True)
            self._staging = None
        if self.fresh and getattr(self, "root", self.target) != self.target:
            shutil.rmtree(self.root, ignore_errors=True)
        self._unlock()

    def _unlock(self) -> None:
        self._release()                # (the finalizer runs once)
        self._lock = None
