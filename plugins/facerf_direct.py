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

.. list-table::
   * - emitter_samples
     - integer — emitter samples per pixel sample (default 1)
   * - hide_emitters
     - boolean — camera rays that meet an emitter see black (default false)

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


def shadow_test(scene, si, ds, faces, active=True):
    """Bool: the shadow ray from ``si`` to the emitter sample ``ds`` is blocked, by the near-field rule of the
    module docstring on the skin of ``faces`` (:func:`_faces`)."""
    active = mi.Bool(active)
    ray = si.spawn_ray_to(ds.p)
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

    def sample(self, scene, sampler, ray, medium=None, active=True):
        si = scene.ray_intersect(ray, active)
        valid = mi.Bool(active) & si.is_valid()
        result = mi.Spectrum(0.0)
        if not self.hide_emitters:
            result += dr.select(mi.Bool(active), si.emitter(scene, active).eval(si, active), 0.0)
        faces = _faces(scene)
        bsdf = si.bsdf(ray)
        ctx = mi.BSDFContext()
        for _ in range(self.emitter_samples):
            ds, weight = scene.sample_emitter_direction(si, sampler.next_2d(valid), False, valid)
            ok = valid & (ds.pdf != 0.0)
            lit = ok & ~shadow_test(scene, si, ds, faces, ok)
            value = bsdf.eval(ctx, si, si.to_local(ds.d), lit)
            result += dr.select(lit, value * weight, 0.0) * (1.0 / self.emitter_samples)
        seen = si.is_valid() | (mi.Bool(not self.hide_emitters) & (scene.environment() is not None))
        return result, mi.Bool(active) & seen, []

    def aov_names(self):
        return []

    def to_string(self):
        return f"FaceRFDirect[emitter_samples={self.emitter_samples}]"


mi.register_integrator("facerf_direct", lambda props: FaceRFDirect(props))
