"""Eyes and teeth (paper §6.3): one reference expression each, with ray-traced visibility.

The captured expressions cannot sample how eyelids and lips shadow the eyes and teeth,
so these parts are not blended: each is rendered from a single **reference expression**
(the one where it is most visible — ``eyes_wide_open``, ``teeth_bared``) and every light
direction's visibility is ray-traced against the *target* geometry (lids over eyes, lips
over teeth)::

    I(p) = Σ_l L_l(R_Δ) · V_l(p) · F_ref(x_ref(p))[l]

where ``p`` is a point on the target's part, ``x_ref`` its place in the reference's
camera images (the same point in the part's rigid rest frame), ``R_Δ`` the part's
rotation from the target to the reference (lighting and view rotate with it, §6.1) and
``V_l`` the visibility of light ``l`` from ``p``.

**Beyond the paper — the dominant source's own data.** The model also keeps the parts of every
captured expression where they are seen (at least a tenth as many pixels as in the reference,
:func:`part_sources`). A frame whose expression weights near a part (the mouth's or the eye's
margin vertices) give one such expression at least half the weight renders that part from that
expression instead of the reference (:func:`frame_reference`): a captured expression, or a blend
dominated by one, then shows its own teeth, eyes and mouth — the lookups land on the same
texels, and the visibility ``V_l`` only re-applies shadows its data already holds.

Eyes: the captured sharp corneal highlights are removed from the reference data
(:func:`remove_specular_peaks`: a light whose response stands far above its light-stage
neighbours' is clamped to them) and re-synthesised as a glossy cornea lit by the same
environment: ``F_schlick(n·v) · E_blur(reflect(−v, n)) · V``.

Geometry: eyes are spheres (template centre and radius; registration gives each
expression's centres; rotation = the head's), teeth the template's strips (two triangles
per tooth) moved by each expression's rigid teeth transforms. The mouth's interior, seen
through the open lips, is a backdrop sphere behind the teeth, rigid with the head and
rendered like the teeth from their reference expression.
"""
from __future__ import annotations

import numpy as np

from ..geometry.rigid import apply
from ..jitarrays import to_jit
from ..variant import ensure_variant
from .jitgeom import CAM_PARAMS, bilinear_taps, camera_params, project

PARTS = ("eye_left", "eye_right", "teeth_upper", "teeth_lower", "mouth_interior")
#: the parts rendered from each reference expression
GROUPS = {"eyes": ("eye_left", "eye_right"), "teeth": ("teeth_upper", "teeth_lower"), "mouth": ("mouth_interior",)}
CORNEA_F0 = 0.025  # (n − 1)² / (n + 1)² for the cornea, n ≈ 1.376
#: the material's cornea lobe: a von Mises–Fisher lobe about the mirror direction, κ = 1 / σ² with σ the blur of
#: the exact path's pre-filtered environment (:func:`.lighting.prefilter`, 0.5 π / 96 rad), so that the lobe
#: integrated against an environment gives the exact path's ``F_schlick(n·v) · E_blur(reflect(−v, n))``
CORNEA_KAPPA = 1.0 / (0.5 * np.pi / 96) ** 2


def sphere_mesh(centre, radius: float, subdivisions: int = 3):
    import trimesh

    s = trimesh.creation.icosphere(subdivisions, radius=radius)
    return np.asarray(s.vertices) + np.asarray(centre), np.asarray(s.faces)


def group_of(part: str) -> str:
    return next(g for g, parts in GROUPS.items() if part in parts)


def frame_reference(part: str, references: dict, sources: dict | None = None,
                    weights: dict | None = None, dominant: float = 0.5) -> str | None:
    """The expression whose data renders ``part`` in a frame.

    ``references`` {group: expression} (models built before the mouth had its own reference render
    the interior from the teeth's); ``sources`` {group: [expressions with the part stored]};
    ``weights`` {group: {expression: weight near the part}}. The source with the largest weight
    wins if that weight is at least ``dominant``; otherwise the reference.
    """
    group = group_of(part)
    if group == "mouth" and group not in references:
        group = "teeth"
    if sources and weights and weights.get(group):
        w = weights[group]
        have = [n for n in sources.get(group, []) if w.get(n, 0.0) > 0]
        if have:
            best = max(have, key=lambda n: w[n])
            if w[best] >= dominant:
                return best
    return references.get(group)


def margin_ids(template: dict) -> dict:
    """{group: template vertex ids round the part} (the mouth's and eyes' hole loops) for the frame weights."""
    holes = template.get("holes") or {}
    out = {}
    for group, names in (("teeth", ("mouth",)), ("mouth", ("mouth",)), ("eyes", ("eye_left", "eye_right"))):
        ids = [int(i) for h in names for i in holes.get(h, [])]
        if ids:
            out[group] = np.array(sorted(set(ids)), np.int64)
    return out


def part_meshes(template: dict) -> dict:
    """Rest-frame meshes {part: (vertices (n, 3), faces (m, 3))} of the template's eyes and teeth."""
    out = {}
    for eye in ("eye_left", "eye_right"):
        if eye in (template.get("eyes") or {}):
            e = template["eyes"][eye]
            out[eye] = sphere_mesh(e["centre"], float(e["radius"]))
    for key, part in (("upper", "teeth_upper"), ("lower", "teeth_lower")):
        t = (template.get("teeth") or {}).get(key)
        if t:
            out[part] = (np.asarray(t["vertices"], np.float64), np.asarray(t["triangles"], np.int64))
    if "teeth_upper" in out:  # the mouth's interior: a backdrop 1 cm behind the front teeth
        teeth = np.concatenate([out[p][0] for p in ("teeth_upper", "teeth_lower") if p in out])
        radius = 0.045
        front = teeth[:, 2].max()
        centre = np.array([teeth[:, 0].mean(), teeth[:, 1].mean(), front - 0.012 - radius])
        out["mouth_interior"] = sphere_mesh(centre, radius, subdivisions=3)
    return out


def part_transforms(template: dict, eye_centres: np.ndarray, teeth: np.ndarray, head_pose: np.ndarray) -> dict:
    """Rest → world 4x4 transforms of the parts in one expression (NaN entries: part absent)."""
    out = {}
    R = np.asarray(head_pose, np.float64)[:3, :3]
    for i, eye in enumerate(("eye_left", "eye_right")):
        if eye in (template.get("eyes") or {}) and np.isfinite(eye_centres[i]).all():
            c = np.asarray(template["eyes"][eye]["centre"], np.float64)
            T = np.eye(4)
            T[:3, :3] = R
            T[:3, 3] = eye_centres[i] - R @ c
            out[eye] = T
    for i, part in enumerate(("teeth_upper", "teeth_lower")):
        if np.isfinite(teeth[i]).all():
            out[part] = np.asarray(teeth[i], np.float64)
    if "teeth_upper" in out:
        out["mouth_interior"] = out["teeth_upper"]  # rigid with the skull
    return out


def remove_specular_peaks(rf: np.ndarray, neighbours: list[np.ndarray], factor: float = 1.6) -> np.ndarray:
    """Clamp each light's response to ``factor`` × the median over its light-stage neighbours.

    rf (N, L, 3) → (N, L, 3). A sharp corneal highlight lights one or two strobes of a
    texel's reflectance function far above their neighbours; diffuse shading varies
    smoothly between neighbouring strobes and is left unchanged.
    """
    lum = rf.mean(axis=2)  # (N, L)
    out = rf.copy()
    for l, nb in enumerate(neighbours):
        ref = np.median(lum[:, nb], axis=1)
        cap_ = factor * ref
        too = lum[:, l] > cap_
        if too.any():
            scale = cap_[too] / np.maximum(lum[too, l], 1e-12)
            out[too, l] *= scale[:, None]
    return out


def light_neighbours(directions: np.ndarray) -> list[np.ndarray]:
    """Each light's neighbours on the light stage (edges of the spherical Delaunay triangulation)."""
    from scipy.spatial import ConvexHull

    tri = ConvexHull(directions).simplices
    nb = [set() for _ in range(len(directions))]
    for a, b, c in tri:
        nb[a] |= {b, c}
        nb[b] |= {a, c}
        nb[c] |= {a, b}
    return [np.array(sorted(s), np.int64) for s in nb]


def skin_in_front_of_parts(scene, ray, si, face_shape, part_shapes, active=True):
    """The Mitsuba-scene form of the renderer's rule that parts belong inside the skin
    (:meth:`.renderer.Renderer._parts_inside_skin`): a ray that meets a part shape first and then, past
    every further part, the *front* of the face shape (the part pokes out through the cheek or a lid)
    shows that skin. Through the mouth or a lid opening the skin behind a part is back-facing and the
    part stays.

    ``scene``: a ``mi.Scene``; ``ray``: the camera rays; ``si``: their first intersections; ``face_shape``
    and ``part_shapes`` (list of ``mi.Shape``). Returns ``(on_face, tri, p)``: whether each lane shows the
    face, and the face triangle and world point it shows there (Dr.Jit values)."""
    import drjit as dr

    mi = ensure_variant()
    face = mi.ShapePtr(face_shape)

    def is_part(hit, mask):
        out = mi.Bool(False)
        for shape in part_shapes:
            out |= mask & hit.is_valid() & (hit.shape == mi.ShapePtr(shape))
        return out

    active = mi.Bool(active)
    on_face = active & si.is_valid() & (si.shape == face)
    tri, p = si.prim_index, si.p
    look = is_part(si, active)
    t = si.t
    for _ in range(2 * len(part_shapes)):   # each closed part: in and out
        # continue along the same line (as the renderer does: 10 µm past the last hit)
        t = t + 1e-5
        nxt = scene.ray_intersect(mi.Ray3f(ray.o + ray.d * t, ray.d), look)
        t = t + nxt.t
        skin_front = look & nxt.is_valid() & (nxt.shape == face) & (dr.dot(nxt.n, ray.d) < 0)
        tri = dr.select(skin_front, nxt.prim_index, tri)
        p = dr.select(skin_front, nxt.p, p)
        on_face |= skin_front
        look = is_part(nxt, look)
    return on_face, tri, p


#: metres a part's shadow and reflection rays start out along its normal (the eye sphere's, a tooth's or
#: the mouth's face normal): clear of the part's own facets and of skin that lies as close (the exact path's
#: rule, :meth:`PartFrame.shade`; ``facerf_direct`` applies it to the material's part hits too)
PART_RAY_OFFSET = 2e-4


#: metres: in :attr:`CombinedScene.rays`, the skin triangles with a corner this close to a part's rest
#: surface (the lids round an eye, the lips and cheeks round the mouth) keep the Phong surface; skin farther
#: off is flat there (docs/rendering.md, "Eighth pass": the parts' rays in a smaller scene)
PART_RAYS_CURVED_RADIUS = 0.02


class CombinedScene:
    """The target's skin template plus its eyes and teeth in one Mitsuba scene, with a part id per triangle
    (0 = skin, 1.. = PARTS index + 1); ``curved`` > 1 traces the skin as its Phong surface
    (:class:`~mifacerf.geometry.meshscene.CurvedMeshScene`).

    Two scenes, posed together (:meth:`set_pose`): :attr:`scene`, the whole surface, for the camera's hits
    (rasterised: no acceleration structure); :attr:`rays`, for the rays cast from the parts (their shadow
    rays, the skin behind a part hit), which Mitsuba traces through a BVH it rebuilds on every pose. With
    ``ray_radius`` (metres) and ``curved`` > 1, :attr:`rays` curves only the skin within ``ray_radius`` of a
    part's vertices (each such triangle's sub-faces exactly the whole surface's: the vertex normals are the
    whole skin's) and keeps the rest of the skin flat — on the demo model 7,895 triangles to build instead of
    17,623; otherwise :attr:`rays` is :attr:`scene`. Both report hits on the same coarse triangles."""

    def __init__(self, skin_vertices, skin_triangles, meshes: dict, curved: int = 1, ray_radius=None):
        from ..geometry.meshscene import CurvedMeshScene, MeshScene

        self.names = [p for p in PARTS if p in meshes]
        verts = [np.asarray(skin_vertices, np.float64)]
        faces = [np.asarray(skin_triangles, np.int64)]
        label = [np.zeros(len(skin_triangles), np.int64)]
        self.rest = {}
        self.offsets = {}
        off = len(verts[0])
        for p in self.names:
            v, f = meshes[p]
            self.rest[p] = v
            self.offsets[p] = (off, len(v))
            verts.append(v)
            faces.append(f + off)
            label.append(np.full(len(f), PARTS.index(p) + 1))
            off += len(v)
        self.n_skin = len(skin_vertices)
        self.label = np.concatenate(label)
        V, F = np.concatenate(verts), np.concatenate(faces)
        # ``curved`` > 1: the skin traced as its Phong surface (the parts flat), hits reported on the coarse mesh
        skin = self.label == 0
        self.scene = MeshScene(V, F) if curved == 1 else CurvedMeshScene(V, F, curved, only=skin)
        self.rays = self.scene
        if curved > 1 and ray_radius is not None and len(self.names):
            from scipy.spatial import cKDTree

            near = cKDTree(V[self.n_skin:]).query(V[: self.n_skin], distance_upper_bound=float(ray_radius))[0]
            near_face = np.zeros(len(F), bool)
            near_face[skin] = np.isfinite(near)[F[skin]].any(axis=1)
            self.rays = CurvedMeshScene(V, F, curved, only=near_face, normals_from=skin)

    def set_pose(self, skin_vertices, transforms: dict, lazy: bool = False) -> np.ndarray:
        """Pose the skin (its vertices) and the parts (``transforms`` {part: 4x4 rest → world}); ``lazy``:
        the Mitsuba scene is updated when next used (:meth:`.meshscene.MeshScene.set_vertices`)."""
        v = self.scene.vertices.copy()
        v[: self.n_skin] = skin_vertices
        for p in self.names:
            o, n = self.offsets[p]
            T = transforms.get(p)
            # a part missing in this pose is moved far away (it cannot be seen or cast shadows)
            v[o:o + n] = apply(T, self.rest[p]) if T is not None else self.rest[p] + 1e3
        self.scene.set_vertices(v, lazy=lazy)
        if self.rays is not self.scene:
            self.rays.set_vertices(v, lazy=lazy)
        return v


#: views-upload entries a renderer keeps for :class:`PartFrame` (the last ones used; each holds the device copies
#: of a frame's part views: a few MB)
PART_FRAME_CACHE = 4


class PartFrame:
    """Device state to shade eye and teeth hits of one frame (see the module docstring).

    ``fields``: {part: {"reference": T_ref (4, 4), "cameras": [(c, weight)], "views": per camera
    dict(index (H, W) int rows or −1, depth (H, W), rf rows (N, L, 3))}}; ``lighting``
    {part: (L, 3)}; ``light_dirs`` {part: (L, 3)} world directions in the target;
    ``env_lookup``: for eyes, a callable Vector3f → Color3f (pre-filtered environment).
    ``cache``: an optional dict (the renderer's, one per model) in which the device copies of the views'
    texel images and rows are kept, keyed by which views of which parts in which order: consecutive frames
    that read the same views (a blend from one camera, a drive) upload only the per-frame tables (pose,
    lighting, camera weights), not the 1–2 M texel indices and rows again (:data:`PART_FRAME_CACHE` entries).
    """

    def __init__(self, model_cameras, n_lights: int, parts: dict, env_lookup=None, cache: dict | None = None):
        mi = ensure_variant()
        self.mi = mi
        self.L = n_lights
        self.env_lookup = env_lookup
        self.part_ids = sorted(parts)
        n_parts = len(PARTS)
        tab = np.zeros((n_parts, 12 + 2 * n_lights * 3))  # T_ref (12), lighting (L*3), light dirs (L*3)
        cams = np.zeros((n_parts, 3, 2))  # (camera index, weight)
        slots = []                        # (part slot k, camera slot m, camera c, view) in upload order
        for p, info in parts.items():
            k = PARTS.index(p)
            tab[k, :12] = info["reference"][:3, :4].reshape(-1)
            tab[k, 12:12 + n_lights * 3] = np.asarray(info["lighting"]).reshape(-1)
            tab[k, 12 + n_lights * 3:] = np.asarray(info["light_dirs"]).reshape(-1)
            for m, (c, w, view) in enumerate(info["views"][:3]):
                cams[k, m] = (len(slots), w)
                slots.append((k, m, c, view))
        # the views' ids name them: an entry holds its views, so no other object takes an id while it is kept
        key = tuple((k, m, c, id(view)) for k, m, c, view in slots)
        held = cache.pop(key, None) if cache is not None else None
        if held is None:
            held = self._upload_views(mi, model_cameras, slots, n_parts)
        if cache is not None:
            cache[key] = held                   # the most recently used last
            while len(cache) > PART_FRAME_CACHE:
                cache.pop(next(iter(cache)))
        self.offs, self.cam_table, self.index, self.depth, self.rf = (
            held["offs"], held["cam_table"], held["index"], held["depth"], held["rf"])
        self.table = to_jit(mi.Float, tab.reshape(-1))
        self.stride = tab.shape[1]
        self.cams = to_jit(mi.Float, cams.reshape(-1))
        self.depth_tolerance = 0.004

    @staticmethod
    def _upload_views(mi, model_cameras, slots, n_parts: int) -> dict:
        """The device copies of the views' texel images (index, depth), rows and cameras, in ``slots``' order."""
        index_parts, depth_parts, rf_parts, offs = [], [], [], np.zeros((n_parts, 3), np.int64)
        img_off, row_off = 0, 0
        cam_table = []
        for k, m, c, view in slots:
            cam_table.append(camera_params(model_cameras[c]))
            idx = np.where(view["index"] >= 0, view["index"] + row_off, -1).reshape(-1)
            index_parts.append(idx)
            depth_parts.append(view["depth"].reshape(-1))
            rf_parts.append(np.asarray(view["rf"]))
            offs[k, m] = img_off
            img_off += idx.size
            row_off += len(view["rf"])
        F16 = __import__("drjit").float16_array_t(mi.Float)
        return {"views": [v for _, _, _, v in slots],   # held, so that their ids stay theirs while cached
                "offs": to_jit(mi.UInt32, offs.reshape(-1).astype(np.uint32)),
                "cam_table": to_jit(mi.Float, np.concatenate(cam_table) if cam_table else np.zeros(CAM_PARAMS)),
                "index": to_jit(mi.Int32, np.concatenate(index_parts).astype(np.int32) if index_parts
                                else np.full(1, -1, np.int32)),
                "depth": to_jit(mi.Float, np.concatenate(depth_parts) if depth_parts else np.zeros(1)),
                "rf": to_jit(F16, np.concatenate(rf_parts).reshape(-1) if rf_parts else np.zeros(3))}

    def shade(self, scene, part, q, p, n, view_dir, active=True):
        """Colour (Color3f) of hits on parts: ``part`` (UInt32, PARTS index), rest-frame point ``q``,
        world point ``p`` and normal ``n`` in the target, unit direction to the viewer ``view_dir``;
        shadow rays are traced against ``scene`` (a Mitsuba scene holding the target geometry)."""
        import drjit as dr

        mi = self.mi
        Float, UInt32, Int32 = mi.Float, mi.UInt32, mi.Int32
        active = mi.Bool(active)
        stride, L, L3 = self.stride, self.L, self.L * 3

        def T(e):
            return dr.gather(Float, self.table, part * stride + e, active)

        pr = [T(4 * r) * q.x + T(4 * r + 1) * q.y + T(4 * r + 2) * q.z + T(4 * r + 3) for r in range(3)]
        # per camera: the 4 bilinear taps (row, weight) behind a depth test; weights renormalised
        taps = []
        wsum = Float(0)
        for m in range(3):
            cidx = UInt32(dr.gather(Float, self.cams, (part * 3 + m) * 2, active))
            wc = dr.gather(Float, self.cams, (part * 3 + m) * 2 + 1, active)
            off = dr.gather(UInt32, self.offs, part * 3 + m, active)
            use = active & (wc > 0)

            def P(e):
                return dr.gather(Float, self.cam_table, cidx * CAM_PARAMS + e, use)

            u, v, dist, zc, wi, hi = project(P, pr)
            for pix, wgt, inside in bilinear_taps(u, v, wi, hi, use & (zc > 0)):
                pix = off + pix
                row = dr.gather(Int32, self.index, pix, inside)
                depth = dr.gather(Float, self.depth, pix, inside)
                ok = inside & (row >= 0) & (dr.abs(depth - dist) <= self.depth_tolerance)
                w = dr.select(ok, wc * wgt, 0.0)
                taps.append((UInt32(dr.select(ok, row, 0)) * L3, w, ok))
                wsum += w
        inv = dr.select(wsum > 0, dr.rcp(wsum), 0.0)
        origin = p + n * PART_RAY_OFFSET
        n_lights = dr.opaque(UInt32, L)

        def body(i, r, g, b):
            d = mi.Vector3f(T(12 + L3 + i * 3), T(12 + L3 + i * 3 + 1), T(12 + L3 + i * 3 + 2))
            lit = active & (wsum > 0) & ~scene.ray_test(mi.Ray3f(origin, d), active & (wsum > 0))
            acc = [r, g, b]
            for ch in range(3):
                val = Float(0)
                for row, w, ok in taps:
                    val += w * Float(dr.gather(type(self.rf), self.rf, row + i * 3 + ch, ok & lit))
                acc[ch] = acc[ch] + dr.select(lit, val * inv * T(12 + i * 3 + ch), 0.0)
            return (i + 1, *acc)

        zero = dr.width(q.x)
        state = (dr.opaque(UInt32, 0, zero), dr.opaque(Float, 0, zero), dr.opaque(Float, 0, zero),
                 dr.opaque(Float, 0, zero))
        # lanes that are not a lit part hit leave the loop at once (a caller shading every pixel's sample,
        # e.g. the facerf integrator, would otherwise run all L iterations for each of them: 10x its frame)
        go = active & (wsum > 0)
        _, r, g, b = dr.while_loop(state, lambda i, *_: (i < n_lights) & go, body)
        colour = mi.Color3f(r, g, b)
        if self.env_lookup is not None:  # the re-synthesised cornea highlight (eyes only)
            is_eye = part < 2
            cos = dr.clip(dr.dot(n, view_dir), 0.0, 1.0)
            fresnel = CORNEA_F0 + (1 - CORNEA_F0) * (1 - cos) ** 5
            refl = 2 * dr.dot(n, view_dir) * n - view_dir
            seen = is_eye & active & ~scene.ray_test(mi.Ray3f(origin, refl), is_eye & active)
            colour += dr.select(seen, fresnel * self.env_lookup(refl), 0.0)
        return colour, active & (wsum > 0)


class PartMaterial:
    """Eyes, teeth and mouth interior for the image-based material (``facerf_bsdf``): the response of each
    part to *one* light direction, as :class:`PartFrame` sums it over the light stage.

    Per hit on part ``k`` at world point ``p``, viewer direction ``ω_o`` and light direction ``ω_i``::

        f = Σ_c w_c(R_Δ ω_o) · F_ref,c(x_c(A p))[interp(R_Δ ω_i)]

    with ``A = T_ref · T_target⁻¹`` (3x4: the target's part point in the reference expression's geometry),
    ``R_Δ`` its rotation, ``w_c`` the camera weights of the rotated view (:class:`.views.ViewSampler`,
    cameras without the part's data dropped, renormalised), ``x_c`` the projection into camera ``c``
    (the 2x2 texels whose stored depth lies within ``depth_tolerance`` of the point, as in
    :class:`PartFrame`) and ``interp`` the material's light rule. The visibility ``V_l`` of §6.3 — lids
    over the eyes, lips over the teeth, other objects — is the integrator's shadow ray. The reference of
    each part is chosen per pose as the exact path's (:func:`frame_reference`). The re-synthesised glossy
    cornea highlight of :class:`PartFrame` is a glossy lobe of the eyes (:meth:`cornea`, sampled by
    :meth:`sample_cornea`): ``F_schlick(n·ω_o) · vMF(ω_i; reflect(−ω_o, n), CORNEA_KAPPA)`` with ``n`` the
    eye sphere's normal, its visibility again the shadow ray's (before 2026-12-02 the eyes lacked it: the
    stored eye fields have their sharp highlights removed).

    ``model``: :class:`~.model.Model`; ``lights``: a :class:`.light_interp.LightInterpolator` (on the device).
    """

    def __init__(self, model, lights, depth_tolerance: float = 0.004):
        from .views import ViewSampler

        mi = ensure_variant()
        self.mi = mi
        self.model = model
        self.lights = lights
        self.L = model.n_lights
        self.C = len(model.cameras)
        self.views = ViewSampler.from_cameras(model.cameras)
        self.cam_table = to_jit(mi.Float, np.concatenate([camera_params(c) for c in model.cameras]))
        self.depth_tolerance = depth_tolerance
        self.margins = margin_ids(model.template)
        self.chosen: dict = {}
        self.uploaded_key = None
        self.table = to_jit(mi.Float, np.zeros(len(PARTS) * 12))
        self.eye_centre = to_jit(mi.Float, np.zeros(len(PARTS) * 3))
        self._empty()

    def _empty(self) -> None:
        mi = self.mi
        F16 = __import__("drjit").float16_array_t(mi.Float)
        self.has = to_jit(mi.Float, np.zeros(len(PARTS) * self.C))
        self.offs = to_jit(mi.UInt32, np.zeros(len(PARTS) * self.C, np.uint32))
        self.index = to_jit(mi.Int32, np.full(2, -1, np.int32))
        self.depth = to_jit(mi.Float, np.zeros(2))
        self.rf = to_jit(F16, np.zeros(6))

    def update(self, parts: dict, weights: np.ndarray | None) -> None:
        """A pose: ``parts`` {part: 4x4 rest → world}, ``weights`` (T, S) per-vertex expression weights
        (choose each part's reference, :func:`frame_reference`)."""
        model = self.model
        by_group = None
        if weights is not None:
            by_group = {g: dict(zip(model.expressions, np.asarray(weights)[ids].mean(axis=0)))
                        for g, ids in self.margins.items()}
        refs = {p: frame_reference(p, model.references, model.part_sources, by_group) for p in parts}
        placed = {p: (ref, self._reference_transform(ref, p)) for p, ref in refs.items() if ref is not None}
        chosen = {p: ref for p, (ref, T_ref) in placed.items() if T_ref is not None}
        tab = np.zeros((len(PARTS), 12))
        for p in chosen:   # the target's part point → the reference's: T_ref · T_target⁻¹
            tab[PARTS.index(p)] = (placed[p][1] @ np.linalg.inv(np.asarray(parts[p], np.float64)))[:3, :4].reshape(-1)
        mi = self.mi
        self.table = to_jit(mi.Float, tab.reshape(-1))
        centres = np.zeros((len(PARTS), 3))
        for p in ("eye_left", "eye_right"):   # the target's eye centres (world): the cornea's normals
            if p in parts and p in (model.template.get("eyes") or {}):
                T = np.asarray(parts[p], np.float64)
                centres[PARTS.index(p)] = T[:3, :3] @ np.asarray(model.template["eyes"][p]["centre"]) + T[:3, 3]
        self.eye_centre = to_jit(mi.Float, centres.reshape(-1))
        key = tuple(sorted(chosen.items()))
        if key != self.uploaded_key:
            self._upload(chosen)
            self.uploaded_key = key
        self.chosen = chosen

    def _reference_transform(self, ref: str, part: str):
        """Rest → world 4x4 of ``part`` in expression ``ref`` (None: the part is absent there)."""
        m, s = self.model, self.model.expression_index(ref)
        return part_transforms(m.template, m.eye_centres[s], m.teeth[s], m.head_pose[s]).get(part)

    def _upload(self, chosen: dict) -> None:
        """The part texels of each part's reference, every camera, on the device."""
        model, C, mi = self.model, self.C, self.mi
        has = np.zeros((len(PARTS), C))
        offs = np.zeros((len(PARTS), C), np.uint32)
        index_parts, depth_parts, rf_parts = [], [], []
        img_off, row_off = 0, 0
        for p, ref in chosen.items():
            k = PARTS.index(p)
            for c, cam in enumerate(model.cameras):
                pf = model.part_field(ref, c)
                sel = np.flatnonzero(pf["part"] == k) if pf is not None else np.zeros(0, np.int64)
                if not len(sel):
                    continue
                idx = np.full(cam.height * cam.width, -1, np.int64)
                px = pf["pixels"][sel]
                idx[px[:, 0] * cam.width + px[:, 1]] = np.arange(len(sel)) + row_off
                index_parts.append(idx)
                depth_parts.append(np.asarray(pf["depth"][sel], np.float32))
                rf_parts.append(np.asarray(pf["rf"][sel], np.float16))
                has[k, c] = 1.0
                offs[k, c] = img_off
                img_off += idx.size
                row_off += len(sel)
        if not index_parts:
            self._empty()
            return
        F16 = __import__("drjit").float16_array_t(mi.Float)
        self.has = to_jit(mi.Float, has.reshape(-1))
        self.offs = to_jit(mi.UInt32, offs.reshape(-1))
        self.index = to_jit(mi.Int32, np.concatenate(index_parts).astype(np.int32))
        self.depth = to_jit(mi.Float, np.concatenate(depth_parts))
        self.rf = to_jit(F16, np.concatenate(rf_parts).reshape(-1))

    def evaluate(self, part, p, view, light, active=True):
        """Radiance per unit irradiance (Color3f) of hits on parts: ``part`` (UInt32, :data:`PARTS` index),
        world point ``p``, unit world directions ``view`` and ``light``; 0 where no camera holds the point."""
        import drjit as dr

        mi = self.mi
        Float, UInt32, Int32 = mi.Float, mi.UInt32, mi.Int32
        active = mi.Bool(active)
        A = [dr.gather(Float, self.table, part * 12 + e, active) for e in range(12)]
        pr = [A[4 * r] * p.x + A[4 * r + 1] * p.y + A[4 * r + 2] * p.z + A[4 * r + 3] for r in range(3)]

        def rotate(x):
            return mi.Vector3f(*[A[4 * r] * x.x + A[4 * r + 1] * x.y + A[4 * r + 2] * x.z for r in range(3)])

        cam_ids, cam_w = self.views.weights_jit(rotate(view))
        light_ids, light_w = self.lights.weights_jit(rotate(light), active)
        cw = [dr.select(active, cam_w[m], 0.0) * dr.gather(Float, self.has, part * self.C + cam_ids[m], active)
              for m in range(3)]
        ctot = cw[0] + cw[1] + cw[2]
        cinv = dr.select(ctot > 0, dr.rcp(ctot), 0.0)
        tol = dr.opaque(Float, self.depth_tolerance)
        L3 = self.L * 3
        out = [Float(0), Float(0), Float(0)]
        wsum = Float(0)
        for m in range(3):
            wc = cw[m] * cinv
            use = active & (wc > 0)
            c = cam_ids[m]

            def P(e):
                return dr.gather(Float, self.cam_table, c * CAM_PARAMS + e, use)

            u, v, dist, zc, wi, hi = project(P, pr)
            off = dr.gather(UInt32, self.offs, part * self.C + c, use)
            col = [Float(0), Float(0), Float(0)]
            cov = Float(0)
            for pix, wgt, inside in bilinear_taps(u, v, wi, hi, use & (zc > 0)):
                row = dr.gather(Int32, self.index, off + pix, inside)
                ok = inside & (row >= 0)
                rsel = UInt32(dr.select(ok, row, 0))
                ok &= dr.abs(dr.gather(Float, self.depth, rsel, ok) - dist) <= tol
                tw = dr.select(ok, wgt, 0.0)
                for ch in range(3):
                    for li in range(3):
                        col[ch] += tw * light_w[li] * Float(dr.gather(type(self.rf), self.rf,
                                                                      rsel * L3 + light_ids[li] * 3 + ch, ok))
                cov += tw
            good = use & (cov > 1e-3)
            scale = dr.select(good, wc / cov, 0.0)
            for ch in range(3):
                out[ch] += scale * col[ch]
            wsum += dr.select(good, wc, 0.0)
        inv = dr.select(wsum > 1e-9, dr.rcp(wsum), 0.0)
        return mi.Color3f(out[0] * inv, out[1] * inv, out[2] * inv)

    # ---------------------------------------------------------- the cornea
    def _mirror(self, part, p, view, active):
        """(is an eye, the Fresnel weight F_schlick(n·ω_o), the mirror direction reflect(−ω_o, n)) at eye hits."""
        import drjit as dr

        mi = self.mi
        eye = mi.Bool(active) & (part < 2)
        c = mi.Point3f(*[dr.gather(mi.Float, self.eye_centre, part * 3 + d, eye) for d in range(3)])
        n = dr.normalize(p - c)
        cos = dr.dot(n, view)
        fresnel = CORNEA_F0 + (1 - CORNEA_F0) * (1 - dr.clip(cos, 0.0, 1.0)) ** 5
        return eye & (cos > 0), fresnel, 2 * cos * n - view

    def cornea(self, part, p, view, light, active=True):
        """The cornea lobe's value (Float, the same in every channel; 0 off the eyes) for light direction ``light``."""
        import drjit as dr

        eye, fresnel, mirror = self._mirror(part, p, view, active)
        return dr.select(eye, fresnel * vmf_pdf(mirror, light, CORNEA_KAPPA), 0.0)

    def cornea_pdf(self, part, p, view, light, active=True):
        """Density (solid angle) of :meth:`sample_cornea` at ``light`` (0 off the eyes)."""
        import drjit as dr

        eye, _, mirror = self._mirror(part, p, view, active)
        return dr.select(eye, vmf_pdf(mirror, light, CORNEA_KAPPA), 0.0)

    def sample_cornea(self, part, p, view, u2, active=True):
        """World directions drawn from the cornea lobe about the mirror direction (``u2``: Point2f)."""
        _, _, mirror = self._mirror(part, p, view, active)
        return vmf_sample(mirror, u2, CORNEA_KAPPA)


def vmf_pdf(mean, d, kappa: float):
    """von Mises–Fisher density on the sphere about unit ``mean`` at unit directions ``d`` (Dr.Jit arrays);
    ``1 − mean·d`` as half the squared distance, for precision at large ``kappa``."""
    import drjit as dr

    one_minus = 0.5 * dr.squared_norm(d - mean)
    norm = float(kappa / (2 * np.pi * (1 - np.exp(-2 * kappa))))
    return norm * dr.exp(-kappa * one_minus)


def vmf_sample(mean, u2, kappa: float):
    """Directions drawn from the von Mises–Fisher lobe about unit ``mean`` (Wood's inversion), ``u2`` in [0, 1)²."""
    import drjit as dr

    mi = ensure_variant()
    xi = dr.maximum(u2.x, 1e-7)
    w = 1 + dr.log(xi + (1 - xi) * float(np.exp(-2 * kappa))) / float(kappa)
    w = dr.clip(w, -1.0, 1.0)
    r = dr.safe_sqrt(1 - w * w)
    phi = float(2 * np.pi) * u2.y
    frame = mi.Frame3f(mean)
    return frame.to_world(mi.Vector3f(r * dr.cos(phi), r * dr.sin(phi), w))


# ----------------------------------------------------------------- model build
def visible_part_pixels(reg, name: str, template: dict, triangles, meshes: dict, cameras, scene=None,
                        size: int = 64) -> dict:
    """{part: number of pixels (over all cameras, at ``size``² resolution) where it is seen in expression ``name``}."""
    r = reg.expression(name)
    T = part_transforms(template, r.eye_centres, r.teeth, r.head_pose)
    scene = scene or CombinedScene(r.vertices, triangles, meshes)
    scene.set_pose(r.vertices, T)
    counts = {p: 0 for p in scene.names}
    for cam in cameras:
        hits, _ = scene.scene.render_hits(cam.resized(size, size), spp=1)
        label = scene.label[hits.tri[hits.valid]]
        for p in scene.names:
            counts[p] += int((label == PARTS.index(p) + 1).sum()) if p in T else 0
    return counts


def part_visibility(reg, names: list[str], template: dict, triangles, cameras) -> dict:
    """{expression: {group: pixels where the group's parts are seen}} (ray cast from every camera at 64²)."""
    meshes = part_meshes(template)
    if not meshes:
        return {}
    scene = CombinedScene(reg.expression(names[0]).vertices, triangles, meshes)
    out = {}
    for n in names:
        seen = visible_part_pixels(reg, n, template, triangles, meshes, cameras, scene)
        out[n] = {g: int(sum(seen.get(p, 0) for p in parts)) for g, parts in GROUPS.items()}
    return out


def choose_references(visibility: dict) -> dict:
    """The reference expression of the eyes, of the teeth and of the mouth's interior: the expression where
    each is most visible (paper §6.3). The interior gets its own (an open mouth) rather than the teeth's
    (bared teeth hide it)."""
    out = {}
    for group in GROUPS:
        best = max(visibility, key=lambda n: visibility[n].get(group, 0), default=None)
        if best is not None and visibility[best].get(group, 0) > 0:
            out[group] = best
    return out


def part_sources(visibility: dict, references: dict, fraction: float = 0.1) -> dict:
    """{group: [expressions]}: where the group is seen in at least ``fraction`` of its reference's pixels."""
    out = {}
    for group, ref in references.items():
        need = fraction * visibility[ref][group]
        out[group] = [n for n in visibility if visibility[n].get(group, 0) >= need]
    return out


def build_part_fields(writer, reg, template: dict, triangles: np.ndarray, cameras, sources: dict,
                      light_directions: np.ndarray) -> dict:
    """Write the eye, teeth and mouth fields of their source expressions (model folder,
    ``fields/<expression>/<cam>.parts*``).

    ``sources``: {group: [expressions]} (:func:`part_sources`). Returns {expression: [parts stored]}.
    """
    import os

    meshes = part_meshes(template)
    if not meshes:
        return {}
    wanted: dict[str, list] = {}
    for group, names in sources.items():
        for name in names:
            wanted.setdefault(name, []).extend(p for p in GROUPS[group] if p in meshes)
    neighbours = light_neighbours(light_directions)
    stored = {}
    for ref, want in wanted.items():
        r = reg.expression(ref)
        T = part_transforms(template, r.eye_centres, r.teeth, r.head_pose)
        want = [p for p in want if p in T]
        if not want:
            continue
        cs = CombinedScene(r.vertices, triangles, meshes)
        cs.set_pose(r.vertices, T)
        for cam in cameras:
            hits, _ = cs.scene.render_hits(cam, spp=1)
            sel = np.flatnonzero(hits.valid)
            label = cs.label[hits.tri[sel]]
            keep = np.isin(label, [PARTS.index(p) + 1 for p in want])
            sel, label = sel[keep], label[keep] - 1
            rows, cols = sel // cam.width, sel % cam.width
            rf = reg.field(ref, cam.name)[:, rows, cols].transpose(1, 0, 2)
            eyes = label < 2
            if eyes.any():
                rf[eyes] = remove_specular_peaks(rf[eyes], neighbours)
            base = writer.root / "fields" / ref / cam.name
            base.parent.mkdir(parents=True, exist_ok=True)
            tmp = base.with_name(f".{cam.name}.parts.tmp.npz")
            np.savez_compressed(tmp, pixels=np.stack([rows, cols], 1).astype(np.int32), part=label.astype(np.int8),
                                depth=hits.t[sel].astype(np.float32))
            os.replace(tmp, base.with_suffix(".parts.npz"))
            tmp = base.with_name(f".{cam.name}.parts.tmp.npy")
            np.save(tmp, rf.astype(np.float16))
            os.replace(tmp, base.with_suffix(".parts.rf.npy"))
        stored[ref] = want
    return stored


# ------------------------------------------------------------- target parts
def rotation_blend(Rs: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to Σ w_i R_i: the polar factor, never a reflection."""
    M = np.einsum("i,ijk->jk", w, Rs)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def blend_transforms(Ts: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted blend of rigid 4x4 transforms (linear translations, polar-factor rotation)."""
    out = np.eye(4)
    out[:3, :3] = rotation_blend(Ts[:, :3, :3], w)
    out[:3, 3] = np.einsum("i,ij->j", w, Ts[:, :3, 3])
    return out


def target_parts_from_weights(model, weights: dict[str, float]) -> dict:
    """Part transforms of a linear blend of captured expressions (the expressions' registered parts, blended)."""
    template = model.template
    idx = [model.expression_index(n) for n in weights]
    w = np.array(list(weights.values()), np.float64)
    out = {}
    per = [part_transforms(template, model.eye_centres[s], model.teeth[s], model.head_pose[s]) for s in idx]
    for p in PARTS:
        have = [(T[p], wi) for T, wi in zip(per, w) if p in T]
        if have:
            Ts = np.stack([h[0] for h in have])
            ws = np.array([h[1] for h in have])
            out[p] = blend_transforms(Ts, ws / ws.sum())
    return out


def _kinds(template: dict) -> list:
    return [v["kind"] for v in template.get("vertices", [])]


def target_parts_from_mesh(model, mesh: np.ndarray) -> dict:
    """Part transforms for an arbitrary target mesh (§4.2): head pose from the ear and nose-bridge points
    (Horn, against the neutral), eyes and upper teeth rigid with the head; the jaw (lower teeth) from
    the lower lip and chin vertices (Horn, against the neutral)."""
    from ..geometry.horn1987 import horn

    template = model.template
    kinds = np.array(_kinds(template))
    s0 = model.expression_index(model.neutral)
    neutral = model.vertices[s0]
    base = part_transforms(template, model.eye_centres[s0], model.teeth[s0], model.head_pose[s0])
    head_ids = np.flatnonzero(np.isin(kinds, ["ear", "nose_bridge"]))
    out = {}
    if len(head_ids) >= 3:
        R, t = horn(neutral[head_ids], mesh[head_ids])
        H = np.eye(4)
        H[:3, :3], H[:3, 3] = R, t
    else:
        H = np.eye(4)
    for p in ("eye_left", "eye_right", "teeth_upper", "mouth_interior"):
        if p in base:
            out[p] = H @ base[p]
    jaw_ids = np.flatnonzero(kinds == "lip_lower")
    chin = np.asarray((template.get("regions") or {}).get("chin", []), np.int64)
    jaw_ids = np.union1d(jaw_ids, chin)
    if "teeth_lower" in base:
        if len(jaw_ids) >= 3:
            R, t = horn(neutral[jaw_ids], mesh[jaw_ids])
            J = np.eye(4)
            J[:3, :3], J[:3, 3] = R, t
            out["teeth_lower"] = J @ base["teeth_lower"]
        else:
            out["teeth_lower"] = H @ base["teeth_lower"]
    return out
