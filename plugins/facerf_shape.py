"""``facerf_face``: Mitsuba shape of a face model — the face mesh and its eyes, teeth and mouth interior.

The geometry comes from the model folder (:mod:`mifacerf.rendering.scene_assets`): nothing to
write or pass beside the folder's path. One mesh holds the skin (the template's triangles, in
order) and the parts (labelled per triangle), posed for the expression and placed by
``to_world``. The ``facerf`` integrator and the ``facerf_bsdf`` material read the pose from this
shape, so changing it through ``mi.traverse`` re-poses all three without reloading the scene.

.. list-table::
   * - model
     - string — path of a model folder (``mifacerf build``); required
   * - expression
     - string — ``name`` or ``name=w,name=w`` (a linear blend; default: the model's neutral)
   * - target
     - string — optional .ply/.npy target mesh in the template's topology (§5 weights per vertex)
   * - to_world
     - transform — the head's rigid pose in the scene (default identity)
   * - parts
     - boolean — include eyes, teeth and mouth interior (default true; models without them have none)
   * - curved
     - integer — the skin's Phong level (the template's triangles split ``curved²`` ways onto the Phong
       surface; 1: the flat triangles). Default: the model's own surface (``surface`` in model.json), the
       one the Python renderer traces and the registration fitted the head's outline against
   * - (bsdf)
     - a ``facerf_bsdf`` (no parameters needed: it takes the model and pose from this shape), or any BSDF

Scene parameters (``mi.traverse(scene)``, prefix the shape's id), each re-posing the face on
``params.update()``:

* ``expression`` — ``mi.Float`` of the model's expression weights, in ``model.expressions`` order
  (a list of numbers works; :meth:`FaceShape.weights` turns a name / ``"a=w,b=w"`` / dict into one);
* ``target`` — ``mi.Float`` of 3T skin vertex coordinates (template topology, model frame): a target mesh;
* ``to_world`` — the rigid pose (:meth:`FaceShape.transform` of a ``mi.ScalarTransform4f`` or 4x4 matrix:
  a plain ``ScalarTransform4f`` works as well but has Mitsuba compile a tiny kernel per distinct pose).

Setting ``expression`` blends captured expressions (``target`` becomes that blend); setting
``target`` alone takes the §5 weights of that mesh. The sizes of every array stay fixed, so an
animation re-uses its compiled kernels.

Example::

    {"type": "facerf_face", "model": "model", "expression": "smile=0.7,neutral=0.3",
     "bsdf": {"type": "facerf_bsdf"}}
"""
from __future__ import annotations

import numpy as np

from mifacerf.variant import ensure_variant

mi = ensure_variant()

import drjit as dr  # noqa: E402

from mifacerf.jitarrays import to_jit  # noqa: E402
from mifacerf.geometry.boubekeur2008 import to_coarse_device  # noqa: E402
from mifacerf.rendering.jitgeom import barycentric  # noqa: E402


def resolve_path(path: str) -> str:
    """A relative path that does not exist from the working directory: through Mitsuba's file resolver (which
    holds the folder of the scene file being loaded), as Mitsuba resolves its own file names."""
    from pathlib import Path

    if path and not Path(path).is_absolute() and not Path(path).exists():
        return str(mi.file_resolver().resolve(path))
    return path


class FaceShape(mi.Mesh):
    """A face model as a Mitsuba mesh (see the module docstring)."""

    def __init__(self, props):
        from mifacerf.rendering.scene_assets import FaceGeometry, open_model
        from mifacerf.rendering.scenefile import read_target_mesh

        if "model" not in props:
            raise ValueError("facerf_face: the 'model' parameter (a model folder) is required")
        self.face = open_model(resolve_path(props["model"]))
        try:
            self.geometry = g = FaceGeometry(self.face, bool(props.get("parts", True)),
                                             props["curved"] if "curved" in props else None)
        except ValueError as exc:
            raise ValueError(f"facerf_face: parameter 'curved': {exc}") from None
        M = np.eye(4)
        if "to_world" in props:
            M = np.asarray(props.get("to_world").matrix, np.float64).reshape(4, 4)
        target = props["target"] if "target" in props else ""
        expression = props["expression"] if "expression" in props else self.face.model.neutral
        try:
            if target:
                pose = g.pose(mesh=read_target_mesh(resolve_path(target)), to_world=M)
            else:
                pose = g.pose(expression=expression, to_world=M)
        except KeyError as exc:
            raise ValueError(f"facerf_face: parameter 'expression': {exc.args[0]}") from None
        except ValueError as exc:
            raise ValueError(f"facerf_face: parameter '{'target' if target else 'expression'}': {exc}") from None
        super().__init__(props.id() or "face", g.n_vertices, len(g.triangles), props)
        self.pose_state = pose
        self.version = 0
        S = len(self.face.model.expressions)
        self.expression = mi.Float(pose.expression if pose.expression is not None else np.full(S, 1.0 / S))
        self.target = to_jit(mi.Float, (pose.target if pose.expression is None else
                                        np.linalg.solve(M[:3, :3], (pose.target - M[:3, 3]).T).T).reshape(-1))
        self.to_world = mi.Transform4f(M.astype(np.float32))
        self._local = pose.target if pose.expression is not None else None
        self.listeners = []
        self._set_buffers(pose, faces=True)
        bsdf = self.bsdf()
        if hasattr(bsdf, "attach"):   # a facerf_bsdf: it follows this shape's pose
            bsdf.attach(self)

    # ------------------------------------------------------------------ state
    def weights(self, spec):
        """A name / ``"a=w,b=w"`` / dict / S numbers → the value to set ``<id>.expression`` to (validated; a
        ``mi.Float`` in device memory, so that no number is baked into a kernel)."""
        return to_jit(mi.Float, self.geometry.expression_vector(spec))

    @staticmethod
    def transform(matrix):
        """The value to set ``<id>.to_world`` to, from a 4x4 matrix-like or a ``mi.ScalarTransform4f``, held in
        device memory (``dr.make_opaque``): assigning a ``ScalarTransform4f`` directly works too, but Mitsuba
        then bakes its numbers into a small kernel that is compiled anew for every distinct pose."""
        M = np.asarray(matrix.matrix if hasattr(matrix, "matrix") else matrix, np.float32).reshape(4, 4)
        m = mi.Matrix4f(M)
        dr.make_opaque(m)
        t = mi.Transform4f(m)
        dr.make_opaque(t)
        return t

    @property
    def label(self) -> np.ndarray:
        """Per triangle: 0 skin, k + 1 the part ``PARTS[k]``."""
        return self.geometry.label

    def coarse_hit(self, prim, p, active=True):
        """Skin hits on this mesh → (template triangle (UInt32), barycentrics there [3 Float]): ``prim`` the mesh
        triangle (``si.prim_index``; skin while ``< geometry.n_skin_faces``), ``p`` the hit point (Point3f).
        On the Phong surface a skin face is one of ``curved²`` in its template triangle
        (:func:`~mifacerf.geometry.boubekeur2008.to_coarse_device`); flat, the triangle itself."""
        active = mi.Bool(active) & (mi.UInt32(prim) < self.geometry.n_skin_faces)
        prim = dr.select(active, mi.UInt32(prim), 0)
        b = barycentric(self._faces, self._vertices, prim, p)
        if self._maps is None:
            return prim, b
        return to_coarse_device(mi, self._maps, prim, b, active)

    def _set_buffers(self, pose, faces: bool = False) -> None:
        params = mi.traverse(self)
        self._vertices = to_jit(mi.Float, pose.vertices.astype(np.float32).reshape(-1))
        params["vertex_positions"] = self._vertices
        if faces:
            g = self.geometry
            self._faces = to_jit(mi.UInt32, g.triangles.astype(np.uint32).reshape(-1))
            params["faces"] = self._faces
            self._maps = None if g.tessellation is None else g.tessellation.device_map(mi)
        params.update()

    def traverse(self, callback):
        super().traverse(callback)
        callback.put("expression", self.expression, mi.ParamFlags.NonDifferentiable)
        callback.put("target", self.target, mi.ParamFlags.NonDifferentiable)
        callback.put("to_world", self.to_world, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        mine = [k for k in keys if k in ("expression", "target", "to_world")]
        if not mine:
            super().parameters_changed(keys)
            return
        g = self.geometry
        M = np.asarray(self.to_world.matrix, np.float64).reshape(4, 4)
        try:
            from mifacerf.rendering.scene_assets import rigid_pose

            rigid_pose(M, f"{self.id()}.to_world")
        except ValueError as exc:
            raise ValueError(f"facerf_face: parameter {exc}") from None
        as_mesh = "target" in mine and "expression" not in mine
        if "expression" not in mine and not as_mesh:   # the pose alone: keep what was posed
            as_mesh = self.pose_state.expression is None
        name = f"{self.id()}.target" if as_mesh else f"{self.id()}.expression"
        try:
            if as_mesh:
                pose = g.pose(mesh=np.asarray(self.target, np.float64), to_world=M)
            else:
                expression = np.asarray(self.expression, np.float64) if "expression" in mine \
                    else self.pose_state.expression
                pose = g.pose(expression=expression, to_world=M)
        except (KeyError, ValueError) as exc:
            raise ValueError(f"facerf_face: parameter {name!r}: {exc.args[0]}") from None
        self.pose_state = pose
        if pose.expression is not None:   # in place: mi.traverse handed these very arrays out
            local = np.linalg.solve(M[:3, :3], (pose.target - M[:3, 3]).T).T
            mi.set_property(self.target, to_jit(mi.Float, local.reshape(-1)))
            mi.set_property(self.expression, to_jit(mi.Float, pose.expression))
        self.version += 1
        self._set_buffers(pose)
        for listener in self.listeners:
            listener(self)

    def to_string(self):
        m = self.face.model
        return (f"FaceShape[model={str(m.root)!r}, vertices={self.geometry.n_vertices}, "
                f"curved={self.geometry.curved}, parts={self.geometry.part_names}]")


mi.register_shape("facerf_face", lambda props: FaceShape(props))
