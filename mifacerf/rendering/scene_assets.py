"""The geometry a Mitsuba scene needs of a face model, computed from the model folder itself.

A scene names the model folder only (``<shape type="facerf_face"><string name="model" .../>``,
:mod:`mifacerf.plugins.facerf_shape`); the face mesh and the eye, teeth and mouth-interior meshes
are built here, in memory, from what every model folder holds (``geometry.npz``: the registered
vertices, eye centres, teeth and head transforms of each expression; ``model.json``: the
template with its part meshes). Nothing is written to the model folder or to a cache, so a
model built before scene files existed works unchanged.

One mesh carries the skin and the parts: the skin's triangles first, then each part of
:data:`.parts.PARTS` the template has, labelled per triangle (:attr:`FaceGeometry.label`: 0 skin,
``k + 1`` part ``PARTS[k]``). The skin is the surface the Python renderer traces for the model
(:attr:`FaceGeometry.curved`, by default the model's own, :attr:`Model.surface`): at a Phong level
``n`` > 1 the template's triangles split ``n²`` ways onto the Phong surface
(:mod:`mifacerf.geometry.boubekeur2008`; the surface the registration fitted the extensions' outlines
against), at level 1 the template's triangles themselves, moved out by the chords' sag on a whole-head
template (:func:`.frame.traced_offset`). Either way a skin hit maps back to a template triangle and its
barycentrics (:attr:`FaceGeometry.parent` and its tessellation's map; on the device, ``facerf_face``'s
``coarse_hit``), where the fields are shaded. The vertex and triangle counts are fixed for a model, so an animation changes
vertex positions only: a part a pose lacks collapses onto the skin's centre (zero-area triangles,
never hit).

A pose (:meth:`FaceGeometry.pose`) is an expression — a name, ``"name=w,..."``, a dict or a
weight vector in the model's expression order (a linear blend, paper §4.3) — or a target mesh in
the template's topology (§5 weights per vertex), placed by a rigid ``to_world`` transform (the
head's pose in the scene; the per-vertex rotations into the sources then include it, so the
lighting turns with the head).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..geometry.rigid import apply
from .parts import PARTS, part_meshes


@dataclass
class FacePose:
    """One pose of a face in a scene: ``target`` (T, 3) posed skin vertices, ``weights`` (T, S) expression
    weights, ``parts`` {part: 4x4 rest → world, posed}, ``vertices`` (V, 3) of the whole mesh,
    ``expression`` (S,) the blend weights (None for a target mesh). ``target`` is the template's skin (what is
    shaded); the first vertices of ``vertices`` are the traced skin's (:attr:`FaceGeometry.n_skin_mesh_vertices`)."""

    target: np.ndarray
    weights: np.ndarray
    parts: dict
    vertices: np.ndarray
    expression: np.ndarray | None


_MODELS: dict = {}
_LOCK = threading.Lock()


def open_model(path):
    """The :class:`~.api.FaceModel` of a model folder, opened once per process and shared by the scene's
    shape, material and integrator (one field cache). Raises ``ModelError``/``FileNotFoundError`` naming
    the folder."""
    from .api import FaceModel

    root = Path(str(path)).expanduser().resolve()
    if not (root / "model.json").exists():
        raise FileNotFoundError(f"model folder {str(path)!r} not found (no {root / 'model.json'}); build one with "
                                "'mifacerf build CAPTURE -o MODEL'")
    key = (str(root), (root / "model.json").stat().st_mtime_ns)
    with _LOCK:
        if key not in _MODELS:
            _MODELS[key] = FaceModel(root)
        return _MODELS[key]


def rigid_pose(matrix, name: str = "to_world") -> np.ndarray:
    """A 4x4 rigid transform (rotation + translation) from a matrix-like; refuses scale, shear or NaN."""
    M = np.asarray(matrix, np.float64).reshape(4, 4)
    R = M[:3, :3]
    if not np.isfinite(M).all() or np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0 \
            or np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise ValueError(f"{name}: the face's pose must be a rigid transform (rotation and translation only)")
    return M


class FaceGeometry:
    """The scene mesh of a face model (see the module docstring). ``face``: a :class:`~.api.FaceModel`;
    ``parts``: include the eyes, teeth and mouth interior (models without them have none); ``curved``: the
    skin's Phong level (1: flat triangles; None: the model's own surface).

    Counts: ``n_skin_vertices`` / ``n_skin_triangles`` the template's (T, F); ``n_skin_mesh_vertices`` /
    ``n_skin_faces`` the traced skin's in the mesh (``n_skin_faces = F × curved²``; mesh triangle ``i`` is
    skin while ``i < n_skin_faces``); ``parent`` (n_skin_faces,) each skin face's template triangle;
    ``tessellation`` the :class:`~mifacerf.geometry.boubekeur2008.PhongTessellation` (its ``corner_bary``:
    where in that triangle a sub-face lies), None when flat."""

    def __init__(self, face, parts: bool = True, curved: int | None = None):
        from ..geometry.boubekeur2008 import PhongTessellation, check_curved
        from .frame import traced_offset

        self.face = face
        m = face.model
        self.n_skin_vertices = m.n_vertices
        self.n_skin_triangles = len(m.triangles)
        self.curved = check_curved(m.surface["curved"] if curved is None else curved)
        self.offset = traced_offset(m, self.curved)
        F = np.asarray(m.triangles, np.int64)
        if self.curved > 1:
            self.tessellation = t = PhongTessellation(F, m.n_vertices, self.curved)
            skin, self.parent, n_skin = t.faces, t.parent, t.n_sub
        else:
            self.tessellation = None
            skin, self.parent, n_skin = F, np.arange(len(F)), m.n_vertices
        self.n_skin_mesh_vertices = n_skin
        self.n_skin_faces = len(skin)
        meshes = part_meshes(m.template) if (parts and m.references) else {}
        self.part_names = [p for p in PARTS if p in meshes]
        self.rest = {p: meshes[p][0] for p in self.part_names}
        tris = [np.asarray(skin, np.int64)]
        label = [np.zeros(len(skin), np.uint32)]
        self.offsets = {}
        off = n_skin
        for p in self.part_names:
            v, f = meshes[p]
            self.offsets[p] = (off, len(v))
            tris.append(np.asarray(f, np.int64) + off)
            label.append(np.full(len(f), PARTS.index(p) + 1, np.uint32))
            off += len(v)
        self.n_vertices = off
        self.triangles = np.concatenate(tris)
        self.label = np.concatenate(label)

    # ------------------------------------------------------------------ input
    def expression_vector(self, spec) -> np.ndarray:
        """Blend weights (S,) in the model's expression order from a name, ``"a=w,b=w"``, a dict or a sequence
        of S numbers; validated (known names, finite, non-negative, positive sum) and normalised."""
        from .api import parse_weights

        names = self.face.model.expressions
        if isinstance(spec, (str, dict)):
            w = parse_weights(spec, names)
            return np.array([w.get(n, 0.0) for n in names])
        v = np.asarray(spec, np.float64).reshape(-1)
        if v.shape != (len(names),):
            raise ValueError(f"expression weights: {v.size} values given, the model has {len(names)} expressions "
                             f"({', '.join(names)})")
        if not np.isfinite(v).all() or (v < 0).any() or v.sum() <= 0:
            raise ValueError("expression weights must be finite and non-negative with a positive sum")
        return v / v.sum()

    def target_array(self, mesh, name: str = "target") -> np.ndarray:
        """(T, 3) skin vertices of a target mesh given as (T, 3) or a flat 3T sequence; refuses another topology."""
        v = np.asarray(mesh, np.float64)
        T = self.n_skin_vertices
        if v.size != 3 * T:
            raise ValueError(f"{name}: a target mesh of {v.size // 3 if v.size % 3 == 0 else v.size / 3} vertices; "
                             f"the template has {T} (its topology, in vertex order)")
        v = v.reshape(T, 3)
        if not np.isfinite(v).all():
            raise ValueError(f"{name}: the target mesh has NaN/Inf vertices")
        return v

    # ------------------------------------------------------------------- pose
    def pose(self, expression=None, mesh=None, to_world=None) -> FacePose:
        """The posed mesh of an expression (blend) or of a target mesh; ``to_world`` a rigid 4x4 (default identity)."""
        face = self.face
        M = np.eye(4) if to_world is None else rigid_pose(to_world)
        if mesh is not None:
            local = self.target_array(mesh)
            parts = face.parts(mesh=local)
            weights = face.model.blend.dense_weights(local[None])[0]
            vector = None
        else:
            vector = self.expression_vector(face.model.neutral if expression is None else expression)
            spec = {n: w for n, w in zip(face.model.expressions, vector) if w > 0}
            local, weights = face.target(spec)
            parts = face.parts(spec)
        target = apply(M, local)
        posed = {p: M @ T for p, T in parts.items()}
        vertices = np.empty((self.n_vertices, 3))
        traced = self.offset(target)
        vertices[: self.n_skin_mesh_vertices] = traced if self.tessellation is None else \
            self.tessellation.positions(traced)
        centre = target.mean(axis=0)
        for p in self.part_names:
            o, n = self.offsets[p]
            vertices[o:o + n] = apply(posed[p], self.rest[p]) if p in posed else centre
        return FacePose(target, weights, {p: T for p, T in posed.items() if p in self.part_names}, vertices, vector)
