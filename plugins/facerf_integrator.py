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

The face needs no material under this integrator: a ``facerf_bsdf`` on it serves only the nested
integrator's bounces from other objects onto the face, and reads each source expression's fields and
ray-traces their self-visibility when first used (``scenes/face_envmap.xml`` gives the face none).

The face is the scene's ``facerf_face`` shape (:mod:`.facerf_shape`): its model, expression and
pose are read from it at every render, so an animation sets them through ``mi.traverse`` and
renders again without reloading. Its eyes, teeth and mouth interior (part-labelled triangles of
that mesh) are shaded as §6.3's, with visibility ray-traced against the whole scene.

.. list-table::
   * - model
     - string — optional: a model folder, checked at load (the face shape names the one rendered)
   * - face
     - string — optional id of the ``facerf_face`` shape (default: the scene's first)
   * - environment
     - string — optional generated name or lat-long file; default: the scene's infinite emitter
   * - method, rank
     - string, integer — how fields are stored and lit, a ``COMPRESSION_METHODS`` name
       (:mod:`mifacerf.rendering.compression`; default ``exact``; ``pca`` with ``rank`` coefficients)
   * - light_basis
     - string — the environment → light-stage rule, a ``LIGHT_BASIS_METHODS`` name
       (:mod:`mifacerf.environment`; default ``voronoi``, or ``hat``)
   * - light_epsilon, depth_tolerance, lights
     - float, float, string — the Python ``Renderer``'s skips by its names: lights below ``light_epsilon``
       × the brightest light's weight everywhere are left out (default 1e-4; 0 keeps every light), the
       texel depth test (metres, default 0.004), a light subset ``"i,j,..."`` (methods with light subsets)
   * - (nested)
     - integrator — for everything but the face (default ``path``, max_depth 2)

Example::

    {"type": "scene", "integrator": {"type": "facerf", "integrator": {"type": "path", "max_depth": 2}},
     "face": {"type": "facerf_face", "model": "model", "expression": "smile=0.7,neutral=0.3"},
     "sky": {"type": "envmap", "filename": "sky.exr"}, ...}
"""
from __future__ import annotations

import numpy as np

from mifacerf.variant import ensure_variant

mi = ensure_variant()

import drjit as dr  # noqa: E402



def _environment_of(scene, spec: str | None, height: int = 128, previous=None):
    """The lighting environment: a named/file environment, or the scene's infinite emitter averaged over each
    texel of a ``height``-row lat-long grid (:func:`mifacerf.environment.sample_emitter`). ``previous``: the
    environment this returned for the last frame; it is returned again when the emitter's radiance at the grid's
    texel centres is the same to the bit (so that the renderer's rotated light basis, built per environment, is
    built once for an animation, and again only when the emitter's parameters change; the centres cost 3 ms, the
    texel means 30 ms, so only a changed emitter pays for the means)."""
    from mifacerf.environment import Environment, resolve, sample_emitter

    if spec:   # named or read from a file: the same for every frame
        return previous if previous is not None else resolve(spec)
    for em in scene.emitters():
        if _is_environment(em):
            probe = sample_emitter(em, height, sub=1)
            seen = getattr(previous, "probe", None) if previous is not None else None
            if previous is not None and previous.name == "scene-emitter" and seen is not None and \
                    seen.shape == probe.shape and np.array_equal(seen, probe):
                return previous
            env = Environment(sample_emitter(em, height), "scene-emitter")   # each texel the emitter's mean over it
            env.probe = probe
            return env
    others = ", ".join(_emitter_name(em) for em in scene.emitters())
    raise ValueError("the facerf integrator needs an environment: give 'environment' or put an "
                     "infinite emitter (envmap, constant, sunsky) in the scene"
                     + (f"; the exact path cannot evaluate the scene's {others}: light the face with them "
                        "through the facerf_bsdf material and the direct or path integrator" if others else ""))


def _emitter_name(em) -> str:
    """``'<id>' (<kind>)`` of a Mitsuba emitter, for messages."""
    kind = str(em).split("[", 1)[0].strip() or type(em).__name__    # PointLight, SpotLight, DirectionalEmitter, ...
    return f"emitter {em.id()!r} ({kind})" if em.id() else f"{kind} emitter"


def finite_emitters(scene) -> list[str]:
    """Names of the scene's emitters that are not infinite (point, spot, directional, area): the exact path does
    not light the face with them (the nested integrator still lights the rest of the scene)."""
    return [_emitter_name(em) for em in scene.emitters() if not _is_environment(em)]


def _is_environment(em) -> bool:
    """An infinite emitter evaluated by direction (envmap, constant, sunsky), not a delta one (directional)."""
    f = em.flags()
    return mi.has_flag(f, mi.EmitterFlags.Infinite) and not mi.has_flag(f, mi.EmitterFlags.DeltaDirection)


def _face_shape(scene, face_id: str | None):
    """The scene's ``facerf_face`` shape (the one with id ``face_id`` if given)."""
    from mifacerf.plugins.facerf_shape import FaceShape

    faces = [s for s in scene.shapes() if isinstance(s, FaceShape)]
    if face_id:
        faces = [s for s in faces if s.id() == face_id]
    if not faces:
        what = f"a facerf_face shape with id {face_id!r}" if face_id else "a facerf_face shape"
        raise ValueError(f"facerf: the scene has no {what} (<shape type=\"facerf_face\"> with the model folder)")
    return faces[0]


def skin_in_front_of_parts(scene, ray, si, face_shape, label, n_parts: int, active=True):
    """The rule that parts belong inside the skin (:func:`mifacerf.rendering.parts.skin_in_front_of_parts`)
    on the one ``facerf_face`` mesh, whose triangles carry a part label (``label``: UInt32 per triangle, 0
    skin): a ray that meets a part first and then, past every further part, the *front* of the skin shows
    that skin. Returns ``(on_skin, tri, p, on_part, part)``."""
    face = mi.ShapePtr(face_shape)
    active = mi.Bool(active)

    def lab(hit, mask):
        ok = mask & hit.is_valid() & (hit.shape == face)
        return ok, dr.gather(mi.UInt32, label, hit.prim_index, ok)

    on_face, k = lab(si, active)
    on_skin = on_face & (k == 0)
    on_part = on_face & (k > 0)
    part = dr.select(on_part, k - 1, 0)
    tri, p = si.prim_index, si.p
    look = mi.Bool(on_part)
    t = si.t
    for _ in range(2 * n_parts):   # each closed part: in and out
        t = t + 1e-5
        nxt = scene.ray_intersect(mi.Ray3f(ray.o + ray.d * t, ray.d), look)
        t = t + nxt.t
        hit, kk = lab(nxt, look)
        skin_front = hit & (kk == 0) & (dr.dot(nxt.n, ray.d) < 0)
        tri = dr.select(skin_front, nxt.prim_index, tri)
        p = dr.select(skin_front, nxt.p, p)
        on_skin |= skin_front
        look = hit & (kk > 0)
    on_part &= ~on_skin
    return on_skin, tri, p, on_part, part


class FaceRFIntegrator(mi.SamplingIntegrator):
    def __init__(self, props):
        super().__init__(props)
        self.model_path = props["model"] if "model" in props else None
        if self.model_path is not None:   # a missing folder is named now, not at the first render
            from mifacerf.rendering.scene_assets import open_model

            open_model(self.model_path)
        self.chosen = {k: props[p] for k, p in (("method", "method"), ("rank", "rank"), ("basis", "light_basis"))
                       if p in props}
        if self.chosen:   # methods by name, checked now (defaults: load_model's renderer)
            from mifacerf.rendering.compression import compression_method
            from mifacerf.environment import LIGHT_BASIS_METHODS
            from mifacerf.methods import lookup

            compression_method(self.chosen.get("method", "exact"))
            lookup(LIGHT_BASIS_METHODS, self.chosen.get("basis", "voronoi"), "light basis")
        # the Python API's skips, by Renderer's names: light_epsilon (0: no light skipped), depth_tolerance,
        # lights (a light subset, "0,3,7": compressed methods with light subsets only)
        if "light_epsilon" in props:
            self.chosen["light_epsilon"] = float(props["light_epsilon"])
            if not self.chosen["light_epsilon"] >= 0:
                raise ValueError(f"facerf: parameter 'light_epsilon' must be >= 0, got {props['light_epsilon']}")
        if "depth_tolerance" in props:
            self.chosen["depth_tolerance"] = float(props["depth_tolerance"])
            if not self.chosen["depth_tolerance"] > 0:
                raise ValueError(f"facerf: parameter 'depth_tolerance' must be > 0, got {props['depth_tolerance']}")
        if "lights" in props:
            try:
                self.chosen["lights"] = np.array([int(x) for x in str(props["lights"]).split(",") if x.strip()])
            except ValueError:
                raise ValueError(f"facerf: parameter 'lights': light indices 'i,j,...', got {props['lights']!r}") \
                    from None
        self._renderers = {}
        self.face_id = props["face"] if "face" in props else None
        self.env_spec = props["environment"] if "environment" in props else None
        nested = None
        for name in props.keys():
            obj = props.get(name)
            if isinstance(obj, mi.Integrator):
                nested = obj
        self.nested = nested or mi.load_dict({"type": "path", "max_depth": 2})
        self.frame = None
        self._env = None
        self._inside = False   # within render(): the frame is planned
        self.face_shape = None
        self.stats = None

    def renderer(self, face):
        """The renderer of a face model, with this integrator's methods (one per model, kept warm)."""
        key = id(face.model)
        if key not in self._renderers:
            if self.chosen:
                from mifacerf.rendering.renderer import Renderer

                self._renderers[key] = Renderer(face.model, **self.chosen)
            else:
                self._renderers[key] = face.renderer
        return self._renderers[key]

    @property
    def face(self):
        """The face model being rendered (the scene's face shape's; before a render: the ``model`` parameter's)."""
        if self.face_shape is not None:
            return self.face_shape.face
        from mifacerf.rendering.scene_assets import open_model

        return open_model(self.model_path) if self.model_path else None

    def prepare(self, scene, sensor):
        """Plan and light the frame for ``sensor`` (called by :meth:`render`)."""
        from mifacerf.rendering.renderer import RenderStats, view_checks
        from mifacerf.rendering.sensors import camera_from_sensor
        from mifacerf.rendering.chunks import plan_frame
        from mifacerf.rendering.parts import PARTS
        from mifacerf.jitarrays import to_jit

        self.face_shape = shape = _face_shape(scene, self.face_id)
        face = shape.face
        renderer = self.renderer(face)
        pose = shape.pose_state
        camera = camera_from_sensor(sensor)
        self.stats = RenderStats()
        # a view far from every capture camera, a collapsed target: warned (RenderWarning), as in Renderer.render
        view_checks(pose.target, camera, face.model.cameras, self.stats)
        plan = plan_frame(face.model, pose.target, pose.weights, camera)
        env = self._env = _environment_of(scene, self.env_spec, previous=self._env)
        ignored = finite_emitters(scene)
        if ignored:
            self.stats.warn(f"facerf: the exact path lights the face with the environment only; "
                            f"{', '.join(ignored)} light the rest of the scene but not the face (use the "
                            f"facerf_bsdf material with the direct or path integrator)")
        self.frame = renderer.light_frame(plan, env, self.stats)
        self._label = to_jit(mi.UInt32, shape.label)
        self.n_parts = len(shape.geometry.part_names)
        parts = pose.parts
        self.part_frame = None
        if parts:
            self.part_frame = renderer.part_frame(parts, camera, renderer.light_basis(env), self.stats,
                                                  pose.weights)
            inv = np.zeros((len(PARTS), 16))
            centres = np.zeros((len(PARTS), 3))
            tmpl = face.model.template
            for p, T in parts.items():
                k = PARTS.index(p)
                inv[k] = np.linalg.inv(T).reshape(-1)
                if p.startswith("eye"):
                    centres[k] = T[:3, :3] @ np.asarray(tmpl["eyes"][p]["centre"], np.float64) + T[:3, 3]
            self._part_inv = to_jit(mi.Float, inv.reshape(-1))
            self._part_centre = to_jit(mi.Float, centres.reshape(-1))

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if self._inside:   # Mitsuba's base render calls this override once more (its trampoline): planned already
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        s = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        self.prepare(scene, s)
        self._inside = True
        try:
            return super().render(scene, s, seed, spp, develop, evaluate)
        finally:
            self._inside = False

    def sample(self, scene, sampler, ray, medium=None, active=True):
        active = mi.Bool(active)
        si = scene.ray_intersect(ray, active)
        # a part poking out through the skin in front of the camera shows the skin (parts.py)
        on_face, tri, p_face, on_part, part = skin_in_front_of_parts(scene, ray, si, self.face_shape, self._label,
                                                                     self.n_parts, active)
        tri, b = self.face_shape.coarse_hit(tri, p_face, on_face)   # the template triangle (Phong: of its sub-face)
        bary = mi.Vector3f(*b)
        colour, covered, _ = self.frame.shade(tri, bary, on_face)
        if self.part_frame is not None:
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
        return f"FaceRFIntegrator[face={self.face_id!r}]"


mi.register_integrator("facerf", lambda props: FaceRFIntegrator(props))
