"""The exact environment-lit renderer of a model (paper §6): target → RGBA image.

Per frame (:func:`.chunks.plan_frame` gives the render chunks):

1. the target mesh (template topology, world) is ray cast from the render camera
   (``spp`` stratified samples per pixel, box filter) → per sample a triangle and
   barycentrics;
2. per chunk (source ``s``, capture camera ``c``): the field's texels are lit with the
   per-vertex rotated lighting (:func:`.relight.lit_texels`, a sum over all lights) into
   a lit image in camera ``c``'s pixels;
3. each sample is shaded by :meth:`.frame.LitFrame.shade` (one Dr.Jit kernel, shared
   with the Mitsuba integrator plugin): the same surface point in every chunk's source
   geometry, projected into the chunk's camera, its lit image read bilinearly behind a
   depth test, weighted by the interpolated chunk weight and renormalised.

No shadow is ever traced for the skin: the reflectance fields hold their own
self-shadowing. Output: (H, W, 4) float32, linear sRGB premultiplied by alpha, the share of each pixel's
samples that hit the target geometry (:func:`.frame.resolve_pixels`: anti-aliased, no holes where no field
covers a hit — those take the nearest covered pixel's colour).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..environment import DEFAULT_LIGHT_BASIS_METHOD, LIGHT_BASIS_METHODS, Environment
from ..methods import lookup
from ..jitarrays import aligned_empty, from_jit, to_jit
from ..variant import ensure_plugins, ensure_variant
from .chunks import FramePlan, plan_frame
from .frame import LitFrame, facing_weights, resolve_pixels, traced_offset
from .lighting import RotatedLightBasis
from .relight import DeviceLighting, cpu_kernel
from ..geometry.boubekeur2008 import check_curved
from ..geometry.meshscene import CurvedMeshScene, MeshScene
from ..geometry.rigid import apply
from ..blas import single_threaded_blas
from .parts import (PART_RAYS_CURVED_RADIUS, PARTS, CombinedScene, PartFrame, frame_reference, margin_ids,
                    part_meshes, part_transforms)
from .compression import COMPRESSION_METHODS, DEFAULT_COMPRESSION_METHOD, compression_method


@dataclass
class RenderStats:
    """What a render did: seconds per stage, chunks and texels processed, fields loaded."""

    times: dict = field(default_factory=dict)
    chunks: int = 0
    texels: int = 0
    fields_loaded: list = field(default_factory=list)
    fallback_samples: int = 0
    unseen_samples: int = 0     # hit samples no field covers (their colour: the nearest covered pixel's)
    filled_pixels: int = 0      # pixels with hits but no covered sample, filled that way (frame.resolve_pixels)
    lights_skipped: int = 0
    cached: bool = False
    #: renders the model cannot answer (view far outside the capture cameras, a collapsed target, parts
    #: with no skin around them): one message each; also issued as a :class:`RenderWarning`
    warnings: list = field(default_factory=list)

    def add_time(self, stage: str, seconds: float) -> None:
        self.times[stage] = self.times.get(stage, 0.0) + seconds

    def warn(self, message: str) -> None:
        import warnings

        self.warnings.append(message)
        warnings.warn(message, RenderWarning, stacklevel=3)


class RenderWarning(UserWarning):
    """A render that cannot be right (docs/reliability.md): counted in :attr:`RenderStats.warnings`."""


#: a view whose direction from the head is farther than this from every capture camera's is outside
#: what the captured fields can answer (warned, still rendered)
VIEW_WARN_DEG = 45.0
#: a target whose bounding box is smaller than this (metres) in every axis is collapsed: nothing is drawn
DEGENERATE_TARGET_M = 1e-4


def view_checks(target: np.ndarray, camera: Camera, cameras, stats: RenderStats) -> bool:
    """Warn about renders outside the model's reach; False when nothing should be drawn (collapsed target)."""
    target = np.asarray(target, np.float64)
    if target.ndim != 2 or not target.size or not np.isfinite(target).all():
        return True        # the frame plan refuses these with a ValueError
    extent = np.ptp(target, axis=0)
    if extent.max() < DEGENERATE_TARGET_M:
        stats.warn(f"degenerate target mesh (all vertices within {extent.max():.2g} m): nothing drawn")
        return False
    centre = target.mean(axis=0)
    d = camera.centre - centre
    dirs = np.array([c.centre - centre for c in cameras], np.float64)
    if len(dirs) and np.linalg.norm(d) > 0:
        cos = dirs @ d / (np.linalg.norm(dirs, axis=1) * np.linalg.norm(d) + 1e-12)
        angle = float(np.degrees(np.arccos(np.clip(cos.max(), -1.0, 1.0))))
        if angle > VIEW_WARN_DEG:
            stats.warn(f"view {angle:.0f} deg from the nearest capture camera (bound {VIEW_WARN_DEG:g}): "
                       "outside what the captured fields can answer")
    return True


#: part surfaces a ray may pass on its way to the skin behind a part hit (Renderer._parts_inside_skin)
PART_LAYERS = 4


class Renderer:
    """Renders a :class:`~.model.Model` with the exact environment-lit path.

    ``depth_tolerance`` (m): how far behind a field's seen surface a point may lie and
    still count as visible in that field. ``method``: how fields are stored and lit, a
    :data:`.compression.COMPRESSION_METHODS` name (``exact``, ``pca`` with ``rank`` coefficients, or ``sh``
    with spherical harmonics of order ``rank``);
    ``basis``: the environment → light-stage rule, a :data:`mifacerf.environment.LIGHT_BASIS_METHODS`
    name (``voronoi``). ``curved``: 1 traces the target's triangles flat; ``n`` > 1 traces its Phong surface
    split ``n`` times per edge (:class:`~mifacerf.geometry.meshscene.CurvedMeshScene`; hits and shading stay
    on the coarse mesh); None (the default): the model's own (:attr:`Model.surface`, the surface its
    registration fitted the outlines against).
    """

    def __init__(self, model, depth_tolerance: float = 0.004, method: str = DEFAULT_COMPRESSION_METHOD,
                 rank: int = 8, lights: np.ndarray | None = None, light_epsilon: float = 1e-4,
                 cache_frames: bool = True, basis: str = DEFAULT_LIGHT_BASIS_METHOD, curved: int | None = None):
        self.compression = compression_method(method)
        lookup(LIGHT_BASIS_METHODS, basis, "light basis")
        if lights is not None and not self.compression.light_subsets:
            subsets = [n for n, m in COMPRESSION_METHODS.items() if m.light_subsets]
            raise ValueError(f"a light subset is supported by the {' and '.join(subsets)} method only")
        self.model = model
        self.depth_tolerance = depth_tolerance
        self.method = method
        self.rank = rank
        self.basis = basis
        # a subset of the light stage (benchmarks of light count): only these lights' data are used,
        # each standing for its spherical-Voronoi cell among the subset
        self.lights = None if lights is None else np.asarray(lights, np.int64)
        self.light_directions = model.light_directions if lights is None else model.light_directions[self.lights]
        # skip what a frame does not need: lights whose weight is below light_epsilon x the brightest
        # light's for every vertex and source (0 disables); an unchanged frame is returned from cache
        self.light_epsilon = float(light_epsilon)
        self.cache_frames = cache_frames
        self._last = None
        neutral = model.vertices[model.expression_index(model.neutral)]
        # ``curved`` > 1: the target traced as its Phong surface (geometry.boubekeur2008, ``curved`` splits per
        # edge) instead of its flat chords, which lie inside a smooth subject's skin. The default is the
        # model's: its extension outlines were fitted against that surface (registration.extensions), and
        # another one misplaces them by the chords' sag (docs/rendering.md, "Phong surface")
        self.curved = check_curved(model.surface["curved"] if curved is None else curved)
        self._scene = MeshScene(neutral, model.triangles) if self.curved == 1 else \
            CurvedMeshScene(neutral, model.triangles, self.curved)
        meshes = part_meshes(model.template) if model.references else {}
        # the parts' rays into a scene whose skin is curved only round the parts (parts.PART_RAYS_CURVED_RADIUS):
        # its BVH, rebuilt each pose, is the part of a frame's trace that rasterising left (docs/rendering.md)
        self._combined = CombinedScene(neutral, model.triangles, meshes, curved=self.curved,
                                       ray_radius=PART_RAYS_CURVED_RADIUS) if meshes else None
        self._margins = margin_ids(model.template)
        # the traced target when flat: a whole-head template's face vertices moved out by the chords' sag
        # (frame.ChordOffset); a face-only template traces its registered mesh as it is
        self._traced = traced_offset(model, self.curved)
        self._bases: dict[int, tuple[Environment, RotatedLightBasis]] = {}
        self.method_cache: dict = {}   # what a compression method keeps between frames (sh: environment coefficients)
        self._device: dict[tuple[int, int], object] = {}
        self._texel_maps: dict[tuple[int, int], tuple] = {}
        self._cpu_maps: dict[tuple[int, int], tuple] = {}
        # the relight sum on the CPU (relight_cpu, Numba; every method with ``rows``) or Dr.Jit's kernel: None chooses
        # (relight.cpu_kernel: llvm variants with Numba, unless MIFACERF_NUMBA_RELIGHT=0); False: Dr.Jit's
        self.cpu_relight: bool | None = None
        self._part_views: dict[tuple[str, int, str], dict | None] = {}
        self._part_frames: dict = {}   # PartFrame's device copies of the views, by which views (parts.PART_FRAME_CACHE)

    # -------------------------------------------------------------- lighting
    #: rotated light bases kept (the most recently used environments): a sequence lit by a new
    #: environment each frame holds at most this many, not one per frame
    KEPT_BASES = 4

    def light_basis(self, env: Environment) -> RotatedLightBasis:
        """The rotated light-stage basis of ``env`` (kept per environment object, most recent first)."""
        key = id(env)
        entry = self._bases.pop(key, None)
        if entry is None or entry[0] is not env:
            entry = (env, RotatedLightBasis(env, self.light_directions, method=self.basis))
        self._bases[key] = entry          # re-inserted: dicts keep insertion order, the oldest goes first
        while len(self._bases) > self.KEPT_BASES:
            self._bases.pop(next(iter(self._bases)))
        return entry[1]

    def _device_field(self, s: int, c: int):
        """Field (s, c) loaded for lighting by the renderer's method (cached)."""
        key = (s, c)
        if key not in self._device:
            self._device[key] = self.compression.load(self.model, s, c, self.rank, self.lights)
        return self._device[key]

    def _texel_map(self, s: int, c: int, f):
        """Field (s, c)'s texel vertices (N, 3) and what its lit image needs on the device, made once
        (read-only; a frame reads them, never writes): the texels' pixel indices (N,) uint32, their
        coverage (N,) float32 (1; −1 on the field's outline, :func:`.frame.outline_texels`, as
        :func:`.frame.mark_outline` marks it), the depth map (Float, H*W, +inf where no texel) and the same
        depth map on the host ((H*W,) float32, which the CPU relight path hands over)."""
        key = (s, c)
        if key not in self._texel_maps:
            from .frame import outline_texels

            mi = ensure_variant()
            fv = self.model.triangles[f.tri]
            depth = f.depth_map()
            lin = (f.pixels[:, 0] * depth.shape[1] + f.pixels[:, 1]).astype(np.uint32)
            coverage = np.where(outline_texels(depth).reshape(-1)[lin], -1.0, 1.0).astype(np.float32)
            host = np.ascontiguousarray(depth, np.float32).reshape(-1)
            for a in (fv, lin, coverage, host):
                a.flags.writeable = False
            self._texel_maps[key] = (fv, lin, coverage, to_jit(mi.Float, host), host)
        return self._texel_maps[key]

    # ----------------------------------------------------------------- frame
    def light_frame(self, plan: FramePlan, env: Environment, stats: RenderStats | None = None) -> LitFrame:
        """Lighting per (vertex, source) and the lit image of every chunk of ``plan``."""
        model = self.model
        stats = stats if stats is not None else RenderStats()
        t0 = time.perf_counter()
        rotate = self.compression.lighting
        if rotate is None:       # the light stage's basis, rotated per (vertex, source) (lighting.py)
            basis = self.light_basis(env)
            rotate = lambda _renderer, _env, R: basis.rotated(R)  # noqa: E731
        lighting = {}
        for s in plan.sources:
            used = plan.expression_weights[:, s] > 0
            rows = rotate(self, env, plan.rotations[s][used])
            L = np.zeros((model.n_vertices, rows.shape[1], 3), np.float32)
            L[used] = rows
            lighting[s] = L
        keep = None
        if self.light_epsilon > 0 and lighting and self.compression.lighting is None:
            # (L,): the largest weight of each light; reduced over vertices first (contiguous rows, 20x
            # faster than over both axes at once; a maximum is exact in any order)
            peak = np.max([np.abs(L).max(axis=0).max(axis=1) for L in lighting.values()], axis=0)
            kept = np.flatnonzero(peak >= self.light_epsilon * peak.max())
            if len(kept) < len(peak):
                keep = kept
                stats.lights_skipped = int(len(peak) - len(kept))
                lighting = {s: L[:, kept] for s, L in lighting.items()}
        # each source's lighting laid out and uploaded once for all its chunks (one per capture camera)
        lighting = {s: DeviceLighting(L) for s, L in lighting.items()}
        stats.add_time("lighting", time.perf_counter() - t0)
        if self.compression.rows is not None and (cpu_kernel() if self.cpu_relight is None else self.cpu_relight):
            return self._light_frame_cpu(plan, lighting, keep, stats)
        chunks, lit_texels = [], []
        for chunk in plan.chunks:
            s, c = chunk.s, chunk.c
            t0 = time.perf_counter()
            f = self._field_of(chunk, stats)  # the texel map (the memory-mapped exact data is not read for 'pca')
            data = self._device_field(s, c)
            stats.add_time("load", time.perf_counter() - t0)
            t0 = time.perf_counter()
            fv, lin, coverage, depth, _ = self._texel_map(s, c, f)
            wv = chunk.weights + chunk.fallback            # lit wherever either tier may read it
            # the texels on triangles with a weight at a vertex (the others' weight sums are 0), in texel order
            near = np.flatnonzero((wv[model.triangles] > 0).any(axis=1)[f.tri])
            wt = f.bary[near] * wv[fv[near]]
            wsum_t = wt.sum(1)
            keep_t = wsum_t > 0
            active = near[keep_t]
            coef = wt[keep_t] / wsum_t[keep_t, None]
            # launched now, placed below: the chunks' kernels run while the next ones are prepared
            lit = self.compression.lit(data, len(self.light_directions), active, fv[active], coef, lighting[s], keep)
            chunks.append(self._chunk_entry(chunk))
            lit_texels.append((lit, lin[active], coverage[active], depth))
            stats.chunks += 1
            stats.texels += len(active)
            stats.add_time("relight", time.perf_counter() - t0)
        t0 = time.perf_counter()
        images, depths = _lit_images(chunks, lit_texels)
        stats.add_time("relight", time.perf_counter() - t0)
        sources = {s: model.vertices[s] for s in plan.sources}
        return LitFrame(plan.target, model.triangles, chunks, sources, self.depth_tolerance, images=images,
                        depths=depths)

    def _light_frame_cpu(self, plan: FramePlan, lighting: dict, keep, stats: RenderStats) -> LitFrame:
        """:meth:`light_frame`'s chunks lit on the CPU in one call (:func:`.relight_cpu.lit_images`: the
        method's sum, vectorised along each texel's row — the exact path's lights, ``sh``'s coefficients,
        ``pca``'s components: :attr:`.compression.CompressionMethod.rows`), the images made on the host and
        handed to the device once. The same texels and weights as the chunk-by-chunk path; the sums in
        another order (float32 rounding apart, docs/rendering.md)."""
        from .relight_cpu import lit_images

        mi = ensure_variant()
        model = self.model
        t0 = time.perf_counter()
        chunks, fields, maps, depths, chunk_light, lights = [], [], [], [], [], []
        light_index: dict[int, int] = {}     # id of a lighting's rows → its place in ``lights``
        ids, t_rows = keep, 0.0
        weights = np.zeros((len(plan.chunks), model.n_vertices))
        for i, chunk in enumerate(plan.chunks):
            s, c = chunk.s, chunk.c
            f = self._field_of(chunk, stats)
            data = self._device_field(s, c)
            t1 = time.perf_counter()
            field, light, ids = self.compression.rows(data, lighting[s], keep)
            t_rows += time.perf_counter() - t1     # (pca projects the lighting per field: relight's work)
            fields.append(field)
            if id(light) not in light_index:   # a source's chunks share its rows (exact, sh); pca: one per field
                light_index[id(light)] = len(lights)
                lights.append(light)
            chunk_light.append(light_index[id(light)])
            maps.append(self._cpu_map(s, c, f))
            depths.append(self._texel_map(s, c, f)[4])
            weights[i] = chunk.weights + chunk.fallback            # lit wherever either tier may read it
            chunks.append(self._chunk_entry(chunk))
        stats.add_time("load", time.perf_counter() - t0 - t_rows)
        t0 = time.perf_counter() - t_rows
        sizes = [ch["shape"][0] * ch["shape"][1] for ch in chunks]
        images, lit = lit_images(fields, lights, chunk_light, weights, maps, sizes, ids)
        stats.chunks += len(chunks)
        stats.texels += int(lit.sum())
        depth = aligned_empty((max(int(sum(sizes)), 1),), np.float32)
        if depths:
            np.concatenate(depths, out=depth[:int(sum(sizes))])
        else:
            depth[:] = 0
        frame = LitFrame(plan.target, model.triangles, chunks, {s: model.vertices[s] for s in plan.sources},
                         self.depth_tolerance, images=mi.Float(images if len(images) else np.zeros(4, np.float32)),
                         depths=mi.Float(depth))
        stats.add_time("relight", time.perf_counter() - t0)
        return frame

    def _cpu_map(self, s: int, c: int, f) -> tuple:
        """Field (s, c)'s texel map in the forms :func:`.relight_cpu.lit_images` reads, its indices checked
        (made once): bary (N, 3) float32, vertex ids (N, 3) int64, pixel index (N,) int64, coverage (N,)
        float32."""
        key = (s, c)
        if key not in self._cpu_maps:
            from .relight_cpu import check_map

            fv, lin, coverage, _, depth = self._texel_map(s, c, f)
            self._cpu_maps[key] = check_map(f.bary, fv, lin, coverage, self.model.n_vertices, len(depth))
        return self._cpu_maps[key]

    def _field_of(self, chunk, stats: RenderStats):
        """The field (texel map) of ``chunk``'s (source, camera), noted in ``stats.fields_loaded``."""
        f = self.model.field(chunk.s, chunk.c)
        if (f.expression, f.camera) not in stats.fields_loaded:
            stats.fields_loaded.append((f.expression, f.camera))
        return f

    def _chunk_entry(self, chunk) -> dict:
        """``chunk`` as :class:`.frame.LitFrame` takes it (its tiers' weights, image shape and camera)."""
        cam = self.model.cameras[chunk.c]
        return {"s": chunk.s, "c": chunk.c, "weights": chunk.weights, "fallback": chunk.fallback,
                "shape": (cam.height, cam.width), "camera": cam}

    # ------------------------------------------------------------ eyes, teeth
    def part_frame(self, parts: dict, camera: Camera, basis: RotatedLightBasis, stats: RenderStats,
                   expression_weights: np.ndarray | None = None) -> PartFrame:
        """The eyes' and teeth's shading state for target part transforms ``parts`` {part: 4x4 rest→world};
        ``expression_weights`` (T, S) choose each part's source (:func:`.parts.frame_reference`)."""
        model = self.model
        refs = model.references
        weights = None
        if expression_weights is not None:
            weights = {g: dict(zip(model.expressions, np.asarray(expression_weights)[ids].mean(axis=0)))
                       for g, ids in self._margins.items()}
        info, deltas = {}, []   # deltas: each part's rotation in info's order
        look = -camera.forward
        sampler = self._view_sampler()
        for p, T_t in parts.items():
            ref = frame_reference(p, refs, model.part_sources, weights)
            if ref is None:
                continue
            s = model.expression_index(ref)
            T_ref = part_transforms(model.template, model.eye_centres[s], model.teeth[s], model.head_pose[s]).get(p)
            if T_ref is None:
                continue
            R_delta = T_ref[:3, :3] @ T_t[:3, :3].T  # target pose → reference pose
            idx, w = sampler.weights((R_delta @ look)[None])
            views = []
            for c, wc in zip(idx[0], w[0]):
                view = self._part_view(ref, int(c), p) if wc > 0 else None
                if view is None:
                    continue
                cam = model.cameras[int(c)]
                views.append((int(c), float(wc), view))
                if (ref, cam.name + ":parts") not in stats.fields_loaded:
                    stats.fields_loaded.append((ref, cam.name + ":parts"))
            if views:
                info[p] = {"reference": T_ref, "light_dirs": self.light_directions @ R_delta, "views": views}
                deltas.append(R_delta)
        if info:   # the parts' lighting in one call (0.19 ms for five parts; 0.88 ms one by one), row by row the same
            for v, lighting in zip(info.values(), basis.rotated(np.stack(deltas))):
                v["lighting"] = lighting

        def env_lookup(d):
            from ..variant import ensure_variant as _ev

            return _ev().Color3f(*basis._lookup(d))

        return PartFrame(model.cameras, len(self.light_directions), info, env_lookup, cache=self._part_frames)

    def _part_view(self, ref: str, c: int, part: str):
        """Part ``part``'s texels in camera ``c`` of expression ``ref`` as :class:`.parts.PartFrame` reads them
        ({index (H, W) rows or −1, depth (H, W), rf (N, L, 3)}; None where the camera has none), made once
        (read-only: a frame reads them, never writes)."""
        key = (ref, c, part)
        if key not in self._part_views:
            view = None
            pf = self.model.part_field(ref, c)
            sel = np.flatnonzero(pf["part"] == PARTS.index(part)) if pf is not None else ()
            if len(sel):
                cam = self.model.cameras[c]
                index = np.full((cam.height, cam.width), -1, np.int64)
                depth = np.full((cam.height, cam.width), np.inf, np.float32)
                px = pf["pixels"][sel]
                index[px[:, 0], px[:, 1]] = np.arange(len(sel))
                depth[px[:, 0], px[:, 1]] = pf["depth"][sel]
                rf = np.asarray(pf["rf"][sel])
                view = {"index": index, "depth": depth, "rf": rf if self.lights is None else rf[:, self.lights]}
                for a in view.values():
                    a.flags.writeable = False
            self._part_views[key] = view
        return self._part_views[key]

    def _view_sampler(self):
        if not hasattr(self, "_views"):
            from .views import ViewSampler

            self._views = ViewSampler.from_cameras(self.model.cameras)
        return self._views

    # ----------------------------------------------------------------- render
    def render(self, target: np.ndarray, expression_weights: np.ndarray, camera: Camera, env: Environment,
               spp: int = 4, seed: int = 0, frame: int = 0, plan: FramePlan | None = None,
               stats: RenderStats | None = None, parts: dict | None = None) -> np.ndarray:
        """Render (H, W, 4) RGBA of the target (T, 3) with (T, S) expression weights under ``env``.

        ``parts``: the target's eye and teeth transforms {part: 4x4 rest→world}
        (:func:`.parts.target_parts_from_weights` / :func:`.parts.target_parts_from_mesh`); None
        renders the skin only.

        NumPy's BLAS runs single-threaded inside a frame: the frame's products are small ((N, 3) @ (3, 3)
        ray rotations, 4 x 4 Horn eigen-problems), and a multi-threaded OpenBLAS woken for each, beside
        Dr.Jit's own threads on the same cores, made one ray rotation 40x slower (0.2 s instead of 5 ms
        on 2 cores at load 10); the results are the same bit for bit.
        """
        with single_threaded_blas():
            return self._render(target, expression_weights, camera, env, spp, seed, frame, plan, stats, parts)

    def _render(self, target, expression_weights, camera, env, spp, seed, frame, plan, stats, parts):
        import drjit as dr

        mi = ensure_plugins()  # a render registers the plugins too (an idempotent look-up)
        model = self.model
        stats = stats if stats is not None else RenderStats()
        key = None
        if self.cache_frames and plan is None:
            key = _frame_key(target, expression_weights, camera, env, spp, seed, parts)
            if self._last is not None and self._last[0] == key:
                stats.cached = True
                return self._last[1].copy()
        if not view_checks(target, camera, model.cameras, stats):
            return np.zeros((camera.height, camera.width, 4), np.float32)
        t0 = time.perf_counter()
        traced = self._traced(target if plan is None else plan.target)   # alpha and hits (frame.ChordOffset)
        if plan is None:   # only the vertices of triangles facing the camera: every hit is on one (frame.py)
            W = facing_weights(expression_weights, traced, model.triangles, camera.centre)
            plan = plan_frame(model, target, W, camera, frame)
        stats.add_time("plan", time.perf_counter() - t0)
        lit = self.light_frame(plan, env, stats)
        lit.view_origin = camera.centre   # frame.MIN_VIEW_COS: oblique texels only where this view sees them so too

        t0 = time.perf_counter()
        use_parts = bool(parts) and self._combined is not None
        # lazy: rasterised hits need no acceleration structure; Mitsuba's scene (whose BVH it rebuilds on
        # every update) is updated only if rays are cast into it (the parts' shadow rays, a fall-back)
        if use_parts:
            self._combined.set_pose(traced, parts, lazy=True)
            scene = self._combined.scene
        else:
            self._scene.set_vertices(traced, lazy=True)
            scene = self._scene
        uv, origin, dirs = self._camera_rays(camera, spp, seed)
        # as MeshScene.render_hits (culled), the rays kept: rasterised (geometry.raster) or ray-cast
        hits = scene.camera_hits(camera, self._sample_grid(camera, spp, seed), dirs)
        if use_parts and (hits.tri[hits.valid] >= len(model.triangles)).any():
            self._combined.rays.commit()   # rays go into the posed scene now: Mitsuba rebuilds its BVH here
            self._parts_inside_skin(hits, uv, camera, dirs)
        idx = np.flatnonzero(hits.valid)
        n_skin_tri = len(model.triangles)
        on_skin = hits.tri[idx] < n_skin_tri
        stats.add_time("trace", time.perf_counter() - t0)

        t0 = time.perf_counter()
        colour = np.zeros((len(idx), 3))
        covered = np.zeros(len(idx), bool)
        sk = np.flatnonzero(on_skin)
        if sk.size:   # a camera that sees no skin (looking away) has nothing to shade
            c_sk, cov_sk, fell_back = lit.shade(to_jit(mi.UInt32, hits.tri[idx[sk]]),
                                               to_jit(mi.Vector3f, hits.bary[idx[sk]].T))
            dr.eval(c_sk, cov_sk, fell_back)   # one shading kernel (each read-back would run its own)
            colour[sk] = from_jit(c_sk)
            covered[sk] = np.asarray(cov_sk).astype(bool)
            stats.fallback_samples += int(np.asarray(fell_back).sum())
        stats.add_time("shade", time.perf_counter() - t0)

        if use_parts and (~on_skin).any() and not on_skin.any():
            stats.warn("eyes/teeth/mouth seen with no skin around them (the view looks at the head from "
                       "behind or inside): they are drawn floating")
        if use_parts and (~on_skin).any():
            t0 = time.perf_counter()
            pf = self.part_frame(parts, camera, self.light_basis(env), stats, expression_weights)
            pt = np.flatnonzero(~on_skin)
            tri = hits.tri[idx[pt]]
            label = self._combined.label[tri] - 1
            p_world = origin + hits.t[idx[pt], None] * dirs[idx[pt]]
            q = np.empty_like(p_world)
            normal = np.empty_like(p_world)
            fn = self._combined.scene.face_normals()[tri]
            for k, name in enumerate(PARTS):
                sel = label == k
                if not sel.any() or name not in parts:
                    continue
                T = parts[name]
                q[sel] = (p_world[sel] - T[:3, 3]) @ T[:3, :3]
                if name.startswith("eye"):
                    centre = apply(T, np.asarray(model.template["eyes"][name]["centre"], np.float64)[None])[0]
                    nrm = p_world[sel] - centre
                    normal[sel] = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
                else:
                    normal[sel] = fn[sel]
            view = camera.centre - p_world
            view /= np.linalg.norm(view, axis=1, keepdims=True)
            col, cov = pf.shade(self._combined.rays.scene, to_jit(mi.UInt32, label.astype(np.uint32)),
                                to_jit(mi.Point3f, q.T), to_jit(mi.Point3f, p_world.T),
                                to_jit(mi.Vector3f, normal.T), to_jit(mi.Vector3f, view.T))
            dr.eval(col, cov)
            col, cov = from_jit(col), np.asarray(cov).astype(bool)
            # part points that no reference view saw (e.g. the mouth's back hidden by the lips in the
            # reference): the part's mean colour in this frame, so the plate never shows through
            for k in np.unique(label):
                sel = label == k
                fill = col[sel & cov].mean(axis=0) if (sel & cov).any() else np.zeros(3)
                col[sel & ~cov] = fill
            colour[pt] = col
            covered[pt] = True
            stats.add_time("eyes_teeth", time.perf_counter() - t0)
        stats.unseen_samples += int((~covered).sum())

        t0 = time.perf_counter()
        # alpha from the target geometry's hits; hits no field covers take the nearest covered colour
        out, filled = resolve_pixels(idx // spp, colour, covered, camera.height, camera.width, spp)
        stats.filled_pixels += filled
        stats.add_time("resolve", time.perf_counter() - t0)
        if not np.isfinite(out).all():
            raise FloatingPointError("render produced NaN/Inf pixels")
        if key is not None:
            self._last = (key, out.copy())
        return out


    def _camera_rays(self, camera: Camera, spp: int, seed: int):
        """The camera's sample positions (H*W*spp, 2), centre (3,) and unit ray directions (H*W*spp, 3) as
        :class:`CameraRays` (made for the rows asked: the rasterised hits need none, the parts' few), as
        :meth:`.MeshScene.render_hits` makes them; kept for the last few cameras (an animation's camera is
        undistorted once), the undistorted image plane per intrinsics (a moving camera reuses it)."""
        from ..camera import stratified_pixel_samples

        cache = self.method_cache.setdefault("rays", {})
        intrinsics = _intrinsics(camera, spp, seed)
        if intrinsics not in cache:
            if spp == 1:
                jj, ii = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
                uv = np.stack([jj, ii], -1).reshape(-1, 2).astype(np.float64)
            else:
                uv = stratified_pixel_samples(camera.width, camera.height, spp, seed)
            xn = camera.undistort_pixels(uv)
            if len(cache) >= 4:
                cache.pop(next(iter(cache)))
            cache[intrinsics] = (uv, np.concatenate([xn, np.ones((len(xn), 1))], axis=1), {})
        uv, d_cam, posed = cache[intrinsics]
        pose = camera.R.tobytes()
        if pose not in posed:
            posed.clear()
            posed[pose] = CameraRays(d_cam, camera.R)
        return uv, camera.centre, posed[pose]

    def _sample_grid(self, camera: Camera, spp: int, seed: int):
        """The camera's samples on its undistorted image plane, binned for :func:`.raster.camera_hits`
        (:class:`.raster.SampleGrid`), made once per intrinsics beside :meth:`_camera_rays`' plane; None
        where the rasteriser is not available (the hits are then ray-cast)."""
        from ..geometry import raster

        if not raster.available():
            return None
        key = _intrinsics(camera, spp, seed)
        grids = self.method_cache.setdefault("grids", {})
        if key not in grids:
            if len(grids) >= 4:
                grids.pop(next(iter(grids)))
            self._camera_rays(camera, spp, seed)
            grids[key] = raster.SampleGrid(self.method_cache["rays"][key][1][:, :2], camera.width, camera.height)
        return grids[key]

    def _parts_inside_skin(self, hits, uv: np.ndarray, camera: Camera,
                           directions: np.ndarray | None = None) -> None:
        """Eyes, teeth and the mouth's backdrop belong inside the skin: a camera sample that meets a part first
        and then, right behind it, the *front* of the skin (the part pokes out through the cheek or a lid —
        the target's part transforms are estimates) shows that skin instead. Through the mouth or lid
        opening the skin behind a part is seen from inside (back-facing) and the part stays. Updates the
        combined scene's ``hits`` (H*W*spp samples) in place; ``directions``: the samples' rays (H*W*spp, 3),
        made from ``uv`` when not given."""
        n_skin_tri = len(self.model.triangles)
        part = np.flatnonzero(hits.valid & (hits.tri >= n_skin_tri))
        if part.size == 0:
            return
        # the skin behind each part hit, traced in the combined scene's ray scene (posed and built for the
        # parts' shadow rays too) through the parts' own surfaces (an eye: in and out)
        scene = self._combined.rays
        o, d = camera.pixel_rays(uv[part]) if directions is None else (camera.centre, directions[part])
        start = hits.t[part] + 1e-5
        parts = np.arange(len(scene.faces)) >= n_skin_tri
        behind = scene.trace(o + start[:, None] * d, d, max_layers=PART_LAYERS, through=parts)
        ok = behind.valid
        front = np.zeros(len(part), bool)
        front[ok] = np.einsum("nd,nd->n", scene.face_normals()[behind.tri[ok]], d[ok]) < 0
        sel = part[front]
        hits.tri[sel], hits.bary[sel], hits.t[sel] = behind.tri[front], behind.bary[front], start[front] + behind.t[front]


def _lit_images(chunks: list[dict], lit_texels: list[tuple]):
    """The chunks' lit images and depth maps for :class:`.frame.LitFrame`, made on the device: flat Floats,
    H*W*4 (lit RGB, coverage) and H*W per chunk, in order. ``lit_texels`` per chunk: (the lit colours
    (N, 3) — an array, or the compression method's reader whose ``device`` holds the kernel's (r, g, b) —,
    the texels' pixel indices (N,), their coverage (N,), the field's depth map (Float, H*W)). Pixels
    without a texel hold 0; the same values as lit images filled in NumPy, without copying every chunk's
    whole image through the host. One kernel per chunk (evaluated chunk by chunk: one fused kernel of all
    chunks would change with their count and compile anew)."""
    import drjit as dr

    mi = ensure_variant()
    Float, UInt32 = mi.Float, mi.UInt32
    sizes = [ch["shape"][0] * ch["shape"][1] for ch in chunks]
    total = int(sum(sizes))
    images = dr.zeros(Float, max(4 * total, 4))
    depths = dr.zeros(Float, max(total, 1))
    dr.eval(images, depths)
    off = 0
    for size, (lit, pixels, coverage, depth) in zip(sizes, lit_texels):
        # a launched kernel's reader keeps its colours on the device (NumPy arrays also have a
        # ``device`` attribute since NumPy 2: the string "cpu", so only a reader is asked)
        rgb = getattr(lit, "device", None) if callable(lit) else None
        if rgb is None:
            values = np.asarray(lit() if callable(lit) else lit, np.float32)
            rgb = [to_jit(Float, values[:, k]) for k in range(3)]
        if len(pixels):
            at = to_jit(UInt32, (pixels.astype(np.uint32) + np.uint32(off)) * np.uint32(4))
            for k in range(3):
                dr.scatter(images, rgb[k], at + k)
            dr.scatter(images, to_jit(Float, coverage), at + 3)
        dr.scatter(depths, depth, dr.arange(UInt32, size) + dr.opaque(UInt32, off))
        dr.eval(images, depths)
        off += size
    return images, depths


class CameraRays:
    """A camera's unit ray directions in the world, made on demand: ``rays[rows]`` those rows (N, 3),
    ``np.asarray(rays)`` all of them (made once). ``d_cam`` (N, 3) the samples' (x, y, 1) on the undistorted
    image plane, ``R`` (3, 3) world → camera (as :meth:`Camera.pixel_rays`: Rᵀ d_cam, normalised)."""

    def __init__(self, d_cam: np.ndarray, R: np.ndarray):
        self.d_cam, self.R = d_cam, np.asarray(R, np.float64)
        self._all = None

    def __getitem__(self, rows) -> np.ndarray:
        if self._all is not None:
            return self._all[rows]
        return self._directions(self.d_cam[rows])

    def __array__(self, dtype=None, copy=None):
        if self._all is None:
            self._all = self._directions(self.d_cam)
        return self._all if dtype is None or np.dtype(dtype) == self._all.dtype else self._all.astype(dtype)

    def _directions(self, d_cam: np.ndarray) -> np.ndarray:
        from ..geometry.vectors import row_norms

        d = d_cam @ self.R            # as Camera.pixel_rays: R.T @ d_cam for each row
        d /= row_norms(d)[:, None]    # = np.linalg.norm(d, axis=1) bit for bit, 8x faster (0.4 s at 1024² x 4)
        return d


def _intrinsics(camera: Camera, spp: int, seed: int) -> tuple:
    """What a camera's sample plane depends on (:meth:`Renderer._camera_rays`): size, samples, intrinsics."""
    return (camera.width, camera.height, spp, seed, camera.K.tobytes(), np.asarray(camera.dist).tobytes())


def _frame_key(target, weights, camera, env, spp, seed, parts) -> str:
    """A digest of everything a frame depends on (inputs unchanged ⇒ same image)."""
    import hashlib

    h = hashlib.sha1()
    for a in (target, weights, camera.K, camera.dist, camera.R, camera.t):
        h.update(np.ascontiguousarray(a, np.float64).tobytes())
    h.update(f"{camera.width}x{camera.height}|{id(env)}|{env.name}|{spp}|{seed}".encode())
    for k in sorted(parts or {}):
        h.update(k.encode())
        h.update(np.ascontiguousarray(parts[k], np.float64).tobytes())
    return h.hexdigest()
