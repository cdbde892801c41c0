"""``facerf_direct``: direct illumination whose shadow rays let the face's skin through near the hit.

Mitsuba's own ``direct`` integrator with one rule changed, for the ``facerf_bsdf`` material: a shadow ray
that starts on the skin of a ``facerf_face`` shape passes through the skin within ``near_occluders`` metres
of its origin (the material's parameter; other objects, the eyes, teeth and mouth interior, and skin farther
away block it as usual; rays from anything else are Mitsuba's). Why: the captured reflectance fields already
hold the face's near-field self-shadowing, seen on the real surface; the coarse template's facets and folds
block light the real surface received (on the draft model a shadow ray from the side of the nose met another
skin triangle 0.05 mm to 2 cm away while the field shows the light), and a material cannot return light for a
direction its shadow ray blocks. The material divides out the captured self-visibility traced with the same
rule (:func:`mifacerf.rendering.self_visibility.triangle_visibility` ``near``), so what the rule lets through
it does not divide out. Measured in docs/rendering.md ("Near-field shadow rule").

Estimator: one emitter sample per pixel sample (``emitter_samples`` of them), no BSDF sampling (no MIS) —
unbiased for every emitter Mitsuba samples (delta lights, environments, area lights), noisier than
``direct`` on small area lights and on the eyes' glossy cornea lobe. Camera rays that meet an emitter (the
environment behind the face, an area light) show it as ``direct`` does (``hide_emitters``). With
``near_occluders = 0`` (the material's default) it is ``direct`` without BSDF samples.

Eyes, teeth and mouth: their shadow rays are the exact path's (``PartFrame.shade``). They start
:data:`~mifacerf.rendering.parts.PART_RAY_OFFSET` (0.2 mm) out along the part's normal — an eye's *sphere*
normal, not its faceted mesh's —, and under an environment the ray goes along the stage light the material
answers the sampled direction with (the nearest, ``voronoi``), not the direction itself: the parts' fields
hold the reference's shadows per stage light, and a light whose cell a lid only partly shadows is seen whole
or not at all there, so testing directions inside the cell took light the exact path keeps (the eyes came
out 4–9 % darker). The cornea lobe's share keeps the sampled direction's ray (the exact path's mirror ray).
Other emitters (points, spots, areas) are tested along their own direction. ``part_rays`` false: Mitsuba's
rays for the parts too. Measured in docs/rendering.md ("Eyes under the material").

.. list-table::
   * - emitter_samples
     - integer — emitter samples per pixel sample (default 1)
   * - hide_emitters
     - boolean — camera rays that meet an emitter see black (default false)
   * - part_rays
     - boolean — shadow rays from eyes, teeth and mouth start as the exact path's (default true)

Example::

    {"type": "scene", "integrator": {"type": "facerf_direct"},
     "face": {"type": "facerf_face", "model": "model",
              "bsdf": {"type": "facerf_bsdf", "near_occluders": 0.015}},
     "sky": {"type": "envmap", "filename": "sky.exr"}}
"""
from __future__ import annotations

from mifacerf.variant import ensure_variant

mi = ensure_variant()

import drjit as dr  # noqa: E402

from mifacerf.rendering.self_visibility import NEAR_PASSES, NEAR_STEP  # noqa: E402


def _faces(scene):
    """[(face shape, its skin's triangle count, near_occluders)] of the scene's ``facerf_face`` shapes whose
    material has a near-field rule."""
    from mifacerf.plugins.facerf_shape import FaceShape

    out = []
    for s in scene.shapes():
        state = getattr(s.bsdf(), "state", None) if isinstance(s, FaceShape) else None
        near = float(getattr(state, "near_occluders", 0.0) or 0.0)
        if near > 0:
            out.append((s, s.geometry.n_skin_faces, near))
    return out


def _part_faces(scene):
    """[(face shape, its skin's triangle count, its material)] of the scene's ``facerf_face`` shapes whose
    material shades eyes, teeth and mouth (its triangles after the skin's)."""
    from mifacerf.plugins.facerf_shape import FaceShape

    return [(s, s.geometry.n_skin_faces, s.bsdf()) for s in scene.shapes()
            if isinstance(s, FaceShape) and getattr(s.bsdf(), "parts", None) is not None
            and getattr(s.bsdf(), "n_skin_faces", None) is not None]


def part_ray(si, ds, parts, active=True, snap: bool = False):
    """The shadow ray from ``si`` to the emitter sample ``ds``; from a part of ``parts`` (:func:`_part_faces`)
    it starts :data:`~mifacerf.rendering.parts.PART_RAY_OFFSET` out along the part's normal (an eye's sphere
    normal, else the face's), as the exact path's (``PartFrame.shade``), instead of Mitsuba's offset.
    ``snap``: from a part, towards an environment (an infinite emitter), the ray goes along the stage light
    the material answers ``ds.d`` with (its nearest, ``voronoi``; the light stage turned by the part's pose)
    — the exact path's one ray per light, so that the lights' captured shadows and the rays' agree."""
    from mifacerf.rendering.parts import PART_RAY_OFFSET

    ray = si.spawn_ray_to(ds.p)
    # an environment's sample (Mitsuba puts its point beyond the scene's bounding sphere): along its direction
    far = mi.has_flag(ds.emitter.flags(), mi.EmitterFlags.Infinite)
    for shape, n_skin, bsdf in parts:
        own = mi.Bool(active) & (si.shape == mi.ShapePtr(shape)) & (si.prim_index >= n_skin)
        eye, part = bsdf._on_eye(si, own)
        c = mi.Point3f(*[dr.gather(mi.Float, bsdf.parts.eye_centre, part * 3 + k, eye) for k in range(3)])
        n = dr.select(eye, dr.normalize(si.p - c), si.n)
        o = si.p + n * PART_RAY_OFFSET
        d = ds.p - o
        dist = dr.norm(d)
        along = ds.d
        if snap and bsdf.parts.lights.method == "voronoi":
            along = dr.select(far, _stage_light(bsdf.parts, part, ds.d, own & far), ds.d)
        ray.o = dr.select(own, o, ray.o)
        ray.d = dr.select(own, dr.select(far, along, d / dist), ray.d)
        ray.maxt = dr.select(own, dr.select(far, dr.largest(mi.Float), dist * (1 - mi.math.ShadowEpsilon)), ray.maxt)
    return ray


def _stage_light(parts, part, d, active):
    """World direction of the stage light nearest to ``d`` in part ``part``'s reference frame
    (``PartMaterial``: A = T_ref · T_target⁻¹, whose rotation turns target directions into the reference's)."""
    A = [dr.gather(mi.Float, parts.table, part * 12 + e, active) for e in range(12)]
    ref = mi.Vector3f(*[A[4 * r] * d.x + A[4 * r + 1] * d.y + A[4 * r + 2] * d.z for r in range(3)])
    ids, _ = parts.lights.weights_jit(ref, active)
    l = parts.lights.direction_jit(ids[0], active)
    # back to the target: the rotation's transpose
    return dr.normalize(mi.Vector3f(*[A[c] * l.x + A[4 + c] * l.y + A[8 + c] * l.z for c in range(3)]))


def _eye_cornea(si, ds, parts, value, active=True):
    """The cornea lobe's share of ``value`` (the material's eval at ``ds.d``) at eye hits of ``parts``, 0 elsewhere:
    its visibility is the mirror ray's own in the exact path, not a stage light's."""
    out = dr.zeros(mi.Color3f, dr.width(si.p))
    for shape, n_skin, bsdf in parts:
        own = mi.Bool(active) & (si.shape == mi.ShapePtr(shape)) & (si.prim_index >= n_skin)
        eye, part = bsdf._on_eye(si, own)
        lobe = bsdf.parts.cornea(part, si.p, si.to_world(si.wi), ds.d, eye)
        out = dr.select(eye & (value.x + value.y + value.z > 0), lobe, out)
    return out


def shadow_test(scene, si, ds, faces, active=True, parts=(), snap: bool = False):
    """Bool: the shadow ray from ``si`` to the emitter sample ``ds`` is blocked, by the near-field rule of the
    module docstring on the skin of ``faces`` (:func:`_faces`); rays from the eyes, teeth and mouth of
    ``parts`` (:func:`_part_faces`) start as the exact path's (:func:`part_ray`, ``snap`` its)."""
    active = mi.Bool(active)
    ray = part_ray(si, ds, parts, active, snap) if parts else si.spawn_ray_to(ds.p)
    if not faces:
        return scene.ray_test(ray, active)
    near = mi.Float(0.0)
    for shape, n_skin, d in faces:   # the skin's rule applies to rays that start on that skin
        own = active & (si.shape == mi.ShapePtr(shape)) & (si.prim_index < n_skin)
        near = dr.select(own, d, near)
    on_skin = near > 0
    start = mi.Point3f(ray.o)
    blocked = mi.Bool(False)
    live = mi.Bool(active)
    for k in range(NEAR_PASSES):
        hit = scene.ray_intersect(ray, live)
        met = live & hit.is_valid()
        skin = mi.Bool(False)
        for shape, n_skin, _ in faces:
            skin |= (hit.shape == mi.ShapePtr(shape)) & (hit.prim_index < n_skin)
        passed = met & on_skin & skin & (dr.norm(hit.p - start) <= near)
        last = k == NEAR_PASSES - 1
        blocked |= met & (~passed if not last else mi.Bool(True))
        live = passed
        ray = mi.Ray3f(hit.p + ray.d * NEAR_STEP, ray.d, dr.maximum(ray.maxt - hit.t - NEAR_STEP, 0.0), ray.time,
                       ray.wavelengths)
    return blocked


class FaceRFDirect(mi.SamplingIntegrator):
    """Direct illumination with the near-field shadow rule for ``facerf_bsdf`` (see the module docstring)."""

    def __init__(self, props):
        super().__init__(props)
        self.emitter_samples = int(props["emitter_samples"]) if "emitter_samples" in props else 1
        if self.emitter_samples < 1:
            raise ValueError(f"facerf_direct: parameter 'emitter_samples' must be >= 1 (got {self.emitter_samples})")
        self.hide_emitters = bool(props["hide_emitters"]) if "hide_emitters" in props else False
        # shadow rays from the eyes, teeth and mouth start as the exact path's (part_ray); False: Mitsuba's own
        self.part_rays = bool(props["part_rays"]) if "part_rays" in props else True

    def sample(self, scene, sampler, ray, medium=None, active=True):
        si = scene.ray_intersect(ray, active)
        valid = mi.Bool(active) & si.is_valid()
        result = mi.Spectrum(0.0)
        if not self.hide_emitters:
            result += dr.select(mi.Bool(active), si.emitter(scene, active).eval(si, active), 0.0)
        faces = _faces(scene)
        parts = _part_faces(scene) if self.part_rays else []
        bsdf = si.bsdf(ray)
        ctx = mi.BSDFContext()
        for _ in range(self.emitter_samples):
            ds, weight = scene.sample_emitter_direction(si, sampler.next_2d(valid), False, valid)
            ok = valid & (ds.pdf != 0.0)
            if not parts:
                lit = ok & ~shadow_test(scene, si, ds, faces, ok)
                value = dr.select(lit, bsdf.eval(ctx, si, si.to_local(ds.d), lit), 0.0)
            else:   # parts: the exact path's rays — one per stage light, and the cornea's mirror ray its own
                value = bsdf.eval(ctx, si, si.to_local(ds.d), ok)
                cornea = _eye_cornea(si, ds, parts, value, ok)
                lit = ok & ~shadow_test(scene, si, ds, faces, ok, parts, snap=True)
                seen = ok & (cornea.x + cornea.y + cornea.z > 0)
                seen &= ~shadow_test(scene, si, ds, faces, seen, parts)
                value = dr.select(lit, value - cornea, 0.0) + dr.select(seen, cornea, 0.0)
            result += value * weight * (1.0 / self.emitter_samples)
        seen = si.is_valid() | (mi.Bool(not self.hide_emitters) & (scene.environment() is not None))
        return result, mi.Bool(active) & seen, []

    def aov_names(self):
        return []

    def to_string(self):
        return f"FaceRFDirect[emitter_samples={self.emitter_samples}, part_rays={self.part_rays}]"


mi.register_integrator("facerf_direct", lambda props: FaceRFDirect(props))
