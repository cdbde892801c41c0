"""``facerf_bsdf``: the image-based material of a face model, for Mitsuba's own emitters and integrators.

At a hit on the target face it evaluates the blended, pose-rotated reflectance fields for
any light direction (interpolated between the captured light directions) and the
viewer's direction (camera weights per hit), so directional, point and environment
emitters light it through standard integrators (``direct``, ``path``).
:class:`mifacerf.rendering.material.MaterialState` documents the evaluation.

``eval`` returns radiance per unit irradiance, which is Mitsuba's "BSDF × cosine", for hits seen from
outside the head. ``sample`` draws the light direction from a mixture of a cosine-weighted hemisphere
about the shading normal (probability 0.9) and the uniform sphere (0.1, so that light from below the
coarse template's tangent plane — which the reflectance field may still answer — is sampled too); with
``sampling="reflectance"`` (the default) half the samples come from that mixture and half per
light-stage light in proportion to the fields' response at the hit's nearest vertex
(:class:`mifacerf.rendering.material.LightSampling`). ``pdf`` is the density of what ``sample`` draws,
and sample/pdf/eval are consistent (tested with Mitsuba's chi-square harness).

Standard integrators trace shadow rays, and the face mesh shadows itself although the reflectance
fields already hold its self-shadowing; ``self_visibility`` (default on) divides the captured
self-visibility out where it is known (measured in docs/rendering.md). Eyes, teeth and mouth
interior (the labelled part triangles of a ``facerf_face`` shape) answer each light direction from their
reference expression's part fields (:class:`mifacerf.rendering.parts.PartMaterial`), their visibility
(lids, lips, other objects) from the integrator's shadow rays; the eyes add the integrator's glossy cornea
highlight as a lobe about the mirror direction (``PartMaterial.cornea``), a share ``P_CORNEA`` of their
samples drawn from it.

.. list-table::
   * - model
     - string — model folder
   * - expression
     - string — ``name`` or ``name=w,...`` (ignored when ``target`` is set)
   * - target
     - string — optional .ply/.npy target mesh in the template's topology (§5 weights)
   * - light_basis
     - string — light-stage rule, a ``LIGHT_BASIS_METHODS`` name (default ``voronoi``, or ``hat``)
   * - self_visibility
     - boolean — divide the captured self-visibility out (:mod:`mifacerf.rendering.self_visibility`; default true)
   * - visibility_rule
     - string — how the divided-out self-visibility is measured: ``cell`` (default: the unblocked share of
       each light's Voronoi cell — agreement with the exact path under environments) or ``ray`` (the ray
       towards the light itself — a directional or point light along a stage light)
   * - visibility_grid
     - integer — where inside each triangle the self-visibility is known: a barycentric grid of this order
       (default 3: 10 points per triangle, traced from the triangle's surface as the shadow rays are;
       0: at the vertices only, interpolated — the rule before 2026-12-02)
   * - near_occluders
     - float — metres (default 0): the captured self-visibility is traced with the near-field rule of the
       ``facerf_direct`` integrator, whose shadow rays pass through the skin within this distance of their
       origin (the captured fields hold that self-shadowing already; Mitsuba's own integrators have no such
       rule: use it with ``facerf_direct`` only). 0.015 brings the sides of the draft's nose from 13 % dark to
       2 % (docs/rendering.md, "Near-field shadow rule")
   * - visibility_emitter
     - emitter reference — optional: the scene's environment (``envmap`` or ``constant``, by reference:
       ``<ref name="visibility_emitter" id="ENV"/>``, ``{"type": "ref", "id": "ENV"}``). Each light's cell share
       of the divided-out visibility is then weighted by that environment's radiance across the cell (the
       share of the cell's *light* the shadow rays pass) instead of by solid angle; under an environment with
       concentrated light (a window, the sun) the unweighted share brightens the face where a cell is partly
       blocked on its bright side (docs/rendering.md, "The visibility weighted by the environment"). Read once,
       with the face shape's ``to_world`` at that time; cell rule and ``visibility_grid`` > 0 only
   * - sampling
     - string — ``reflectance`` (default: half the samples by the fields' response per light) or ``cosine``
   * - parts
     - boolean — shade eyes, teeth and mouth interior (default true; false: they are black)
   * - depth_tolerance, max_slots
     - float, integer — the texel depth test (metres, default 0.004, as ``Renderer(depth_tolerance=)``) and
       the source expressions kept per vertex (default 4, the largest weights)
   * - method, rank
     - string, integer — stored fields, a ``COMPRESSION_METHODS`` name (default ``exact``; ``pca`` with
       ``rank``: the ``pca<rank>`` files of ``mifacerf compress``, reconstructed at upload)

The shape using this BSDF must be the target mesh (``mifacerf.rendering.scenefile``).
"""
from __future__ import annotations

import numpy as np

from mifacerf.variant import ensure_variant

mi = ensure_variant()

import drjit as dr  # noqa: E402

P_COSINE = 0.9
#: with sampling="reflectance": the share of samples drawn from the cosine + uniform mixture (the rest by reflectance)
P_MIX_COSINE = 0.5
#: on the eyes: the share of the samples drawn from the cornea lobe (:meth:`PartMaterial.sample_cornea`)
P_CORNEA = 0.3
SAMPLING = ("reflectance", "cosine")


class FaceRFBSDF(mi.BSDF):
    """The image-based material of a face model (the module docstring is its manual: parameters and rules).

    Example::

        {"type": "facerf_face", "model": "model", "expression": "smile",
         "bsdf": {"type": "facerf_bsdf", "sampling": "reflectance", "self_visibility": True}}
    """

    def __init__(self, props):
        super().__init__(props)
        from mifacerf.rendering.material import MaterialState
        from mifacerf.rendering.scenefile import read_target_mesh

        self.state = None
        self.shape = None
        self.light_basis = props["light_basis"] if "light_basis" in props else "voronoi"
        from mifacerf.environment import LIGHT_BASIS_METHODS
        from mifacerf.methods import lookup

        lookup(LIGHT_BASIS_METHODS, self.light_basis, "light basis")
        self.self_visibility = bool(props["self_visibility"]) if "self_visibility" in props else True
        self.sampling = props["sampling"] if "sampling" in props else "reflectance"
        if self.sampling not in SAMPLING:
            raise ValueError(f"facerf_bsdf: parameter 'sampling': {self.sampling!r} is not one of "
                             f"{', '.join(SAMPLING)}")
        self.fields = {k: props[k] for k in ("method", "rank") if k in props}
        if self.fields:
            from mifacerf.rendering.compression import compression_method

            compression_method(self.fields.get("method", "exact"))
        self.n_skin_faces = None
        self.parts = None
        self.with_parts = bool(props["parts"]) if "parts" in props else True
        if "visibility_rule" in props:
            from mifacerf.rendering.self_visibility import VISIBILITY_RULES

            if props["visibility_rule"] not in VISIBILITY_RULES:
                raise ValueError(f"facerf_bsdf: parameter 'visibility_rule': {props['visibility_rule']!r} is not "
                                 f"one of {', '.join(VISIBILITY_RULES)}")
            self.fields["visibility_rule"] = props["visibility_rule"]
        for key, cast in (("max_slots", int), ("depth_tolerance", float), ("visibility_grid", int),
                          ("near_occluders", float)):
            if key in props:
                self.fields[key] = cast(props[key])
        if not self.fields.get("near_occluders", 0.0) >= 0:
            raise ValueError(f"facerf_bsdf: parameter 'near_occluders': {self.fields['near_occluders']} m; "
                             "give a distance >= 0 (0: no near-field rule)")
        self.visibility_emitter = None
        if "visibility_emitter" in props:
            self.visibility_emitter = _environment_emitter(props["visibility_emitter"])
            if self.fields.get("visibility_rule", "cell") != "cell":
                raise ValueError("facerf_bsdf: parameter 'visibility_emitter' needs visibility_rule 'cell'")
        if "model" in props:   # standalone: on a mesh of the target (e.g. a PLY written by scenefile)
            from mifacerf.rendering.scene_assets import open_model

            face = open_model(props["model"])
            target = props["target"] if "target" in props else ""
            expression = props["expression"] if "expression" in props else face.model.neutral
            if target:
                verts, W = face.target(mesh=read_target_mesh(target))
            else:
                verts, W = face.target(expression)
            self.state = MaterialState(face.model, verts, W, light_basis=self.light_basis,
                                       self_visibility=self.self_visibility,
                                       visibility_weights=self._visibility_weights(None), **self.fields)
        flags = (mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.DiffuseTransmission
                 | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide)
        self.m_components = [flags]
        self.m_flags = flags

    def attach(self, shape) -> None:
        """Follow a ``facerf_face`` shape: its model and pose (called by the shape when it is built)."""
        from mifacerf.rendering.material import MaterialState

        from mifacerf.jitarrays import to_jit
        from mifacerf.rendering.parts import PartMaterial

        self.shape = shape
        pose = shape.pose_state
        self.n_skin_faces = shape.geometry.n_skin_faces
        if self.state is None or self.state.model is not shape.face.model:
            rotation = np.asarray(shape.to_world.matrix, np.float64).reshape(4, 4)[:3, :3]
            self.state = MaterialState(shape.face.model, pose.target, pose.weights, light_basis=self.light_basis,
                                       self_visibility=self.self_visibility, curved=shape.geometry.curved,
                                       visibility_weights=self._visibility_weights(rotation), **self.fields)
        else:
            self.state.update(pose.target, pose.weights)
        if self.with_parts and shape.geometry.part_names:   # eyes, teeth, mouth interior: their own response
            self.parts = PartMaterial(shape.face.model, self.state.lights, self.state.depth_tolerance)
            self.parts.update(pose.parts, pose.weights)
            self.label = to_jit(mi.UInt32, shape.label)

        def follow(s):
            self.state.update(s.pose_state.target, s.pose_state.weights)
            if self.parts is not None:
                self.parts.update(s.pose_state.parts, s.pose_state.weights)

        shape.listeners.append(follow)

    def _visibility_weights(self, rotation):
        """The cell samples' weights from ``visibility_emitter`` (None without one), the face posed by ``rotation``."""
        if self.visibility_emitter is None:
            return None
        from mifacerf.rendering.self_visibility import emitter_weights

        w = emitter_weights(self.visibility_emitter, rotation)
        if not w.sum() > 0:
            raise ValueError("facerf_bsdf: parameter 'visibility_emitter': the environment is black along every "
                             "direction; nothing to weight the visibility by")
        return w

    # --------------------------------------------------------------- sampling
    @staticmethod
    def _pdf_cosine(wo):
        cos = dr.maximum(wo.z, 0.0)
        return P_COSINE * cos * dr.inv_pi + (1 - P_COSINE) * dr.inv_four_pi

    def _by_reflectance(self) -> bool:
        return self.sampling == "reflectance" and self.state is not None

    def _on_eye(self, si, active=True):
        """(hit on an eye (Bool), its part index): eye hits draw a share :data:`P_CORNEA` from the cornea lobe."""
        if self.parts is None:
            return mi.Bool(False), mi.UInt32(0)
        on_part = mi.Bool(active) & (si.prim_index >= self.n_skin_faces)
        part = dr.gather(mi.UInt32, self.label, si.prim_index, on_part) - 1
        return on_part & (part < 2), part

    def _skin(self, si, active=True):
        """(template triangle, barycentrics or None) of skin hits: on a ``facerf_face`` shape through its map
        (its Phong surface's sub-faces to the template's triangles); on a plain mesh of the target its own
        triangle (barycentrics from the point)."""
        if self.shape is None or self.n_skin_faces is None:
            return si.prim_index, None
        return self.shape.coarse_hit(si.prim_index, si.p, active)

    def _pdf_local(self, si, wo, active=True):
        pdf = self._pdf_cosine(wo)
        if self._by_reflectance():
            tri, bary = self._skin(si, active)
            v = self.state.nearest_vertex(tri, si.p, bary, active)
            light = self.state.sampling.pdf(v, si.to_world(wo), active)
            pdf = P_MIX_COSINE * pdf + (1 - P_MIX_COSINE) * light
        if self.parts is not None:
            eye, part = self._on_eye(si, active)
            lobe = self.parts.cornea_pdf(part, si.p, si.to_world(si.wi), si.to_world(wo), eye)
            pdf = dr.select(eye, P_CORNEA * lobe + (1 - P_CORNEA) * pdf, pdf)
        return pdf

    def sample(self, ctx, si, sample1, sample2, active=True):
        if self.parts is not None:   # eyes: a share P_CORNEA of the samples from the cornea lobe, the rest as below
            eye, part = self._on_eye(si, active)
            lobe = eye & (sample1 < P_CORNEA)
            sample1 = dr.select(eye, dr.select(lobe, sample1 / P_CORNEA, (sample1 - P_CORNEA) / (1 - P_CORNEA)),
                                sample1)
        u = sample1
        if self._by_reflectance():   # a share P_MIX_COSINE of the samples from the cosine mixture, the rest by reflectance
            by_light = sample1 >= P_MIX_COSINE
            u = dr.select(by_light, (sample1 - P_MIX_COSINE) / (1 - P_MIX_COSINE), sample1 / P_MIX_COSINE)
        wo_cos = mi.warp.square_to_cosine_hemisphere(sample2)
        wo_uni = mi.warp.square_to_uniform_sphere(sample2)
        wo = dr.select(u < P_COSINE, wo_cos, wo_uni)
        if self._by_reflectance():
            tri, bary = self._skin(si, active)
            v = self.state.nearest_vertex(tri, si.p, bary, active)
            wo = dr.select(by_light, si.to_local(self.state.sampling.sample(v, u, sample2, active)), wo)
        if self.parts is not None:
            wo_lobe = self.parts.sample_cornea(part, si.p, si.to_world(si.wi), sample2, lobe)
            wo = dr.select(lobe, si.to_local(wo_lobe), wo)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo = wo
        bs.pdf = self._pdf_local(si, wo, active)
        bs.eta = 1.0
        bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
        bs.sampled_component = mi.UInt32(0)
        value = self.eval(ctx, si, wo, active)
        weight = dr.select(bs.pdf > 0, value / bs.pdf, 0.0)
        return bs, weight

    def pdf(self, ctx, si, wo, active=True):
        return self._pdf_local(si, wo, active)

    def eval(self, ctx, si, wo, active=True):
        if self.state is None:
            if self.shape is None:
                raise ValueError("facerf_bsdf: no model: give it a 'model' parameter or use it on a facerf_face shape")
            # attached to a shape whose construction failed (its error was raised then): Dr.Jit still traces
            # every registered BSDF in a later scene's virtual calls, so this instance must stay silent
            return dr.zeros(mi.Color3f, dr.width(si.p))
        view = si.to_world(si.wi)
        light = si.to_world(wo)
        # seen from outside only: a path that entered the head (the sampled uniform-sphere directions) and meets the
        # mesh from inside gets nothing (else light leaked through the head to it: +1.6 % under path, toy model)
        ok = mi.Bool(active) & (dr.squared_norm(view) > 0.5) & (dr.squared_norm(light) > 0.5) & (si.wi.z > 0)
        on_part = mi.Bool(False)
        if self.n_skin_faces is not None:   # on a facerf_face shape: its skin triangles come first
            on_part = ok & (si.prim_index >= self.n_skin_faces)
            ok &= si.prim_index < self.n_skin_faces
        tri, bary = self._skin(si, ok)
        value = self.state.evaluate(tri, si.p, view, light, ok, bary=bary)
        if self.parts is not None:   # eyes, teeth and mouth interior (labelled triangles after the skin's)
            part = dr.gather(mi.UInt32, self.label, si.prim_index, on_part) - 1
            diffuse = self.parts.evaluate(part, si.p, view, light, on_part)
            value = dr.select(on_part, diffuse + self.parts.cornea(part, si.p, view, light, on_part), value)
            ok |= on_part
        return dr.select(ok & dr.isfinite(value.x + value.y + value.z), value, 0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

    def traverse(self, callback):
        pass

    def to_string(self):
        return f"FaceRFBSDF[{len(self.state.used)} source expression(s)]"


def _environment_emitter(obj):
    """``obj`` if it is an infinite emitter Mitsuba can evaluate along a direction, else one clear error."""
    if not isinstance(obj, mi.Emitter):
        raise ValueError(f"facerf_bsdf: parameter 'visibility_emitter' must reference an emitter "
                         f"(<ref name=\"visibility_emitter\" id=\"...\"/>); got {type(obj).__name__}")
    if not mi.has_flag(obj.flags(), mi.EmitterFlags.Infinite) or mi.has_flag(obj.flags(), mi.EmitterFlags.Delta):
        raise ValueError(f"facerf_bsdf: parameter 'visibility_emitter' must be an environment (envmap or "
                         f"constant); got {str(obj).split('[', 1)[0].strip() or type(obj).__name__}")
    return obj


mi.register_bsdf("facerf_bsdf", lambda props: FaceRFBSDF(props))
