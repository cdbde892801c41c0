"""``facerf``: Mitsuba integrator rendering a relightable face model under the scene's environment.

The exact environment-lit path (paper §6): at a primary hit on the face shape it returns
the blended, pose-rotated reflectance fields summed against the rotated light-stage
basis of the scene's environment — noise-free at one sample per pixel apart from
anti-aliasing, and without shadowing the face again (the reflectance fields already
hold the face's self-shadowing). Everything else in the scene (and rays that miss the
face) is rendered by the nested integrator.

Before the kernel runs, :meth:`FaceRFIntegrator.render` plans the frame for the scene's
sensor (render chunks, per-vertex rotations, camera weights) and lights every chunk
(:class:`mifacerf.rendering.frame.LitFrame`); ``sample`` then shades face hits with the
same Dr.Jit kernel as the Python API.

.. list-table::
   * - model
     - string — path of a model folder (``mifacerf build``)
   * - expression
     - string — ``name`` or ``name=w,name=w`` (linear blend); ignored when ``target`` is set
   * - target
     - string — optional path of a .ply/.npy target mesh in the template's topology (§5 weights)
   * - face
     - string — id of the face shape (default ``face``); its vertices must be the target's
   * - (parts)
     - shapes with ids ``eye_left``, ``eye_right``, ``teeth_upper``, ``teeth_lower``, ``mouth_interior``
       (written by :mod:`mifacerf.rendering.scenefile`) are shaded as §6.3's eyes and teeth
   * - environment
     - string — optional generated name or lat-long file; default: the scene's infinite emitter
   * - method, rank
     - string, integer — how fields are stored and lit, a ``COMPRESSION_METHODS`` name
       (:mod:`mifacerf.rendering.compression`; default ``exact``; ``pca`` with ``rank`` coefficients)
   * - light_basis
     - string — the environment → light-stage rule, a ``LIGHT_BASIS_METHODS`` name
       (:mod:`mifacerf.environment`; default ``voronoi``, or ``hat``)
   * - (nested)
     - integrator — for everything but the face (default ``path``, max_depth 2)

Example::

    {"type": "facerf", "model": "model", "expression": "smile=0.7,neutral=0.3",
     "integrator": {"type": "path", "max_depth": 2}}
"""
from __future__ import annotations

import numpy as np

from mifacerf.variant import ensure_variant

mi = ensure_variant()

import drjit as dr  # noqa: E402

from mifacerf.rendering.parts import skin_in_front_of_parts  # noqa: E402


def _environment_of(scene, spec: str | None, height: int = 128):
    """The lighting environment: a named/file environment, or the scene's infinite emitter sampled on a lat-long grid."""
    from mifacerf.environment import Environment, evaluate_emitter, latlong_grid, resolve

    if spec:
        return resolve(spec)
    for em in scene.emitters():
        if mi.has_flag(em.flags(), mi.EmitterFlags.Infinite):
            dirs, _ = latlong_grid(height)
            rad = evaluate_emitter(em, dirs.reshape(-1, 3)).reshape(height, 2 * height, 3)
            return Environment(np.maximum(rad, 0), "scene-emitter")
    raise ValueError("the facerf integrator needs an environment: give 'environment' or put an "
                     "infinite emitter (envmap, constant, sunsky) in the scene")


class FaceRFIntegrator(mi.SamplingIntegrator):
    def __init__(self, props):
        super().__init__(props)
        from mifacerf.rendering.api import load_model

        if "model" not in props:
            raise ValueError("facerf: the 'model' parameter (a model folder) is required")
        self.face = load_model(props["model"])
        chosen = {k: props[p] for k, p in (("method", "method"), ("rank", "rank"), ("basis", "light_basis"))
                  if p in props}
        if chosen:   # methods by name (defaults: load_model's renderer)
            from mifacerf.rendering.renderer import Renderer

            self.face.renderer = Renderer(self.face.model, **chosen)
        self.expression = props.get("expression", None)
        self.target_path = props["target"] if "target" in props else None
        self.face_id = props["face"] if "face" in props else "face"
        self.env_spec = props["environment"] if "environment" in props else None
        nested = None
        for name in props.keys():
            obj = props.get(name)
            if isinstance(obj, mi.Integrator):
                nested = obj
        self.nested = nested or mi.load_dict({"type": "path", "max_depth": 2})
        self.frame = None
        self.face_shape = None
        self.stats = None

    def target(self):
        from mifacerf.rendering.scenefile import read_target_mesh

        if self.target_path:
            return self.face.target(mesh=read_target_mesh(self.target_path))
        return self.face.target(self.expression or self.face.model.neutral)

    def prepare(self, scene, sensor):
        """Plan and light the frame for ``sensor`` (called by :meth:`render`)."""
        from mifacerf.rendering.renderer import RenderStats
        from mifacerf.rendering.sensors import camera_from_sensor
        from mifacerf.rendering.chunks import plan_frame

        shapes = [s for s in scene.shapes() if s.id() == self.face_id]
        if not shapes:
            raise ValueError(f"facerf: the scene has no shape with id {self.face_id!r}")
        self.face_shape = shapes[0]
        target, W = self.target()
        verts = np.asarray(mi.traverse(self.face_shape)["vertex_positions"]).reshape(-1, 3)
        if verts.shape != target.shape or np.abs(verts - target).max() > 1e-4:
            raise ValueError(f"facerf: shape {self.face_id!r} is not the target mesh (vertex count or positions "
                             "differ); write it with mifacerf.rendering.scenefile.write_target_mesh")
        camera = camera_from_sensor(sensor)
        self.stats = RenderStats()
        plan = plan_frame(self.face.model, target, W, camera)
        env = _environment_of(scene, self.env_spec)
        self.frame = self.face.renderer.light_frame(plan, env, self.stats)
        # eyes, teeth and the mouth's interior: shapes with the parts' names, if the scene has them
        from mifacerf.rendering.parts import PARTS
        from mifacerf.jitarrays import to_jit

        parts = self.face.parts(mesh=target) if self.target_path else self.face.parts(
            self.expression or self.face.model.neutral)
        by_id = {s.id(): s for s in scene.shapes()}
        self.part_shapes = [(PARTS.index(p), by_id[p]) for p in PARTS if p in by_id and p in parts]
        self.part_frame = None
        if self.part_shapes:
            self.part_frame = self.face.renderer.part_frame(parts, camera, self.face.renderer.light_basis(env),
                                                            self.stats)
            inv = np.zeros((len(PARTS), 16))
            centres = np.zeros((len(PARTS), 3))
            tmpl = self.face.model.template
            for p, T in parts.items():
                k = PARTS.index(p)
                inv[k] = np.linalg.inv(T).reshape(-1)
                if p.startswith("eye"):
                    centres[k] = T[:3, :3] @ np.asarray(tmpl["eyes"][p]["centre"], np.float64) + T[:3, 3]
            self._part_inv = to_jit(mi.Float, inv.reshape(-1))
            self._part_centre = to_jit(mi.Float, centres.reshape(-1))

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        s = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        self.prepare(scene, s)
        return super().render(scene, sensor, seed, spp, develop, evaluate)

    def sample(self, scene, sampler, ray, medium=None, active=True):
        active = mi.Bool(active)
        si = scene.ray_intersect(ray, active)
        # a part poking out through the skin in front of the camera shows the skin (parts.py)
        on_face, tri, p_face = skin_in_front_of_parts(scene, ray, si, self.face_shape,
                                                      [shape for _, shape in self.part_shapes], active)
        tri = dr.select(on_face, tri, 0)
        bary = self.frame.barycentric(tri, p_face)
        colour, covered, _ = self.frame.shade(tri, bary, on_face)
        on_part = mi.Bool(False)
        part = mi.UInt32(0)
        for k, shape in self.part_shapes:
            hit = active & ~on_face & si.is_valid() & (si.shape == mi.ShapePtr(shape))
            part = dr.select(hit, k, part)
            on_part |= hit
        if self.part_shapes:
            M = [dr.gather(mi.Float, self._part_inv, part * 16 + e, on_part) for e in range(12)]
            p = si.p
            q = mi.Point3f(*[M[4 * r] * p.x + M[4 * r + 1] * p.y + M[4 * r + 2] * p.z + M[4 * r + 3] for r in range(3)])
            c = mi.Point3f(*[dr.gather(mi.Float, self._part_centre, part * 3 + d, on_part) for d in range(3)])
            n = dr.select(part < 2, dr.normalize(p - c), si.n)
            pcol, pcov = self.part_frame.shade(scene, part, q, p, n, -ray.d, on_part)
            colour = dr.select(on_part, pcol, colour)
            covered = dr.select(on_part, True, covered)
            on_face |= on_part
        other, valid, aovs = self.nested.sample(scene, sampler, ray, medium, active & ~on_face)
        result = dr.select(on_face, mi.Spectrum(colour), other)
        return result, dr.select(on_face, covered, valid), aovs

    def aov_names(self):
        return self.nested.aov_names()

    def to_string(self):
        return f"FaceRFIntegrator[face={self.face_id!r}, expression={self.expression!r}]"


mi.register_integrator("facerf", lambda props: FaceRFIntegrator(props))
