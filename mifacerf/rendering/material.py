"""The image-based material: reflectance fields evaluated for *any* light direction, per hit.

Where the exact environment path (:mod:`.frame`) sums fixed light-stage weights, a
BSDF must answer "how much light from direction ω leaves towards the viewer" for
arbitrary ω, so that Mitsuba's own emitters (directional, point, environment) can
light the face through standard integrators. :class:`MaterialState` evaluates, for a
hit at barycentrics b of target triangle (v0, v1, v2), viewer direction ω_o and light
direction ω_i (world)::

    f(ω_i) = Σ_k b_k Σ_slots w_{k,s} Σ_c cw_{k,s,c}(R ω_o) · F_{s,c}(x_{s,c}) [ interp(R ω_i) ]
             / (Σ of the same weights where the field covers x)

with ``R = R_ts`` the vertex's local rotation into source ``s`` (§6.1), ``cw`` the camera
weights of the rotated view (:class:`.views.ViewSampler`, per hit; cameras that do not
see the vertex in ``s`` drop out), ``x_{s,c}`` the projection of the hit's surface point
in the source geometry into camera ``c`` (bilinear over the texels whose seen surface lies within
:data:`DEPTH_TOLERANCE` of the hit, in the exact path's three camera tiers — :meth:`MaterialState.evaluate`;
without that depth test a texel on camera ``c``'s silhouette, bright with a grazing back light, was
blended in where the exact path drops it: the material's 34.4 dB against the exact path), and ``interp`` the
light-stage rule (:class:`.light_interp.LightInterpolator`, named as the exact path's light basis:
``voronoi``, the default — the nearest light, so that an environment is integrated as the exact path
does — or ``hat``, barycentric between the three lights round the direction), divided by the source's captured
self-visibility of that light at the hit (:func:`.self_visibility.triangle_visibility`, a grid inside each
triangle; ``visibility_grid=0``: the per-vertex values interpolated; ``near_occluders``: traced with the
near-field rule of the ``facerf_direct`` integrator's shadow rays; ``visibility_weights``: each light cell's
visible share weighted by the scene environment's radiance in it, not by solid angle). The value is
radiance per unit irradiance — Mitsuba's "BSDF × cosine". Per vertex at most
``max_slots`` source expressions (the largest weights) are kept.

Fields of every used source expression and every camera are held on the device as
float16 rows plus a per-field (H, W) texel-index image.
"""
from __future__ import annotations

import numpy as np

from ..jitarrays import to_jit
from ..variant import ensure_variant
from .frame import OUTLINE_WEIGHT, outline_texels
from .jitgeom import CAM_PARAMS, barycentric, bilinear_taps, camera_params, project
from .light_interp import LightInterpolator
from .relight import to_device_f16
from .self_visibility import GRID_ORDER, MIN_VISIBILITY
from .views import ViewSampler

#: metres: a texel is used for a hit only if the surface its camera saw there lies this close to the hit's
#: distance from that camera (the exact path's occlusion-aware filtering, :class:`.frame.LitFrame`)
DEPTH_TOLERANCE = 0.004


class LightSampling:
    """Light directions drawn in proportion to a hit's response to each light-stage light (``facerf_bsdf``'s
    ``sampling="reflectance"``).

    The sphere is cut into a ``grid_height`` x 2 ``grid_height`` lat-long grid; each grid cell belongs to the
    light nearest to its centre (the light's region, area ``A_l``, close to its Voronoi cell). Per target
    vertex ``v`` a table gives the probability ``P_v(l) ∝ r_v(l) A_l`` of light ``l``, with ``r_v(l)`` the
    mean luminance of the blended fields' texels round ``v`` (weighted by barycentrics, over cameras) — the
    material's value is constant over a light's Voronoi cell, so this is the value × the cell's area. A
    direction is drawn for a hit by taking its nearest vertex's table: a light by inverting ``P_v`` (a
    binary search), a grid cell of that light's region in proportion to its solid angle, a point uniform in
    solid angle in that cell. Density (solid angle): ``P_v(l(ω)) / A_{l(ω)}`` with ``l(ω)`` the owner of
    ω's grid cell. A vertex whose fields are all dark draws by area (uniform on the sphere)."""

    def __init__(self, directions: np.ndarray, grid_height: int = 64):
        from ..environment import latlong_grid

        mi = ensure_variant()
        self.mi = mi
        D = np.asarray(directions, np.float64)
        self.L = len(D)
        self.H, self.W = grid_height, 2 * grid_height
        dirs, solid = latlong_grid(self.H)
        owner = np.argmax(dirs.reshape(-1, 3) @ D.T, axis=1)
        solid = solid.reshape(-1)
        self.area = np.bincount(owner, weights=solid, minlength=self.L)
        order = np.argsort(owner, kind="stable")
        counts = np.bincount(owner, minlength=self.L)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        cdf = np.zeros(len(order))
        for l in range(self.L):
            sl = slice(start[l], start[l] + counts[l])
            c = np.cumsum(solid[order[sl]])
            cdf[sl] = c / max(c[-1], 1e-300) if counts[l] else c
        self.max_count = int(max(counts.max(), 1))
        self.owner = to_jit(mi.UInt32, owner.astype(np.uint32))
        self.area_dev = to_jit(mi.Float, np.maximum(self.area, 1e-12))
        self.cell_of = to_jit(mi.UInt32, order.astype(np.uint32))
        self.cell_cdf = to_jit(mi.Float, cdf)
        self.start = to_jit(mi.UInt32, start.astype(np.uint32))
        self.count = to_jit(mi.UInt32, counts.astype(np.uint32))

    def set_table(self, response: np.ndarray) -> None:
        """Per-vertex response (T, L) ≥ 0 → the per-vertex light probabilities and their CDF (on the device)."""
        q = np.maximum(np.asarray(response, np.float64), 0.0) * self.area[None]
        tot = q.sum(1, keepdims=True)
        dark = tot[:, 0] <= 1e-30
        q[dark] = self.area[None]
        q /= q.sum(1, keepdims=True)
        self.prob = to_jit(self.mi.Float, q.reshape(-1))
        c = np.cumsum(q, axis=1)
        c[:, -1] = 1.0
        self.cdf = to_jit(self.mi.Float, c.reshape(-1))

    def sample(self, v, u, u2, active=True):
        """World directions (Vector3f) for nearest vertices ``v`` (UInt32), ``u`` (Float) and ``u2`` (Point2f)."""
        import drjit as dr

        mi = self.mi
        Float, UInt32 = mi.Float, mi.UInt32
        L = self.L
        base = v * L
        lo, hi = dr.zeros(UInt32, dr.width(u)), dr.full(UInt32, L - 1, dr.width(u))
        for _ in range(int(np.ceil(np.log2(max(L, 2))))):   # the first light whose CDF exceeds u
            mid = (lo + hi) >> 1
            right = dr.gather(Float, self.cdf, base + mid, active) <= u
            lo = dr.select(right & (lo < hi), mid + 1, lo)
            hi = dr.select(~right & (lo < hi), mid, hi)
        light = lo
        first = dr.gather(UInt32, self.start, light, active)
        count = dr.gather(UInt32, self.count, light, active)
        lo, hi = first, first + dr.maximum(count, 1) - 1
        x = u2.x
        for _ in range(int(np.ceil(np.log2(max(self.max_count, 2))))):   # a cell of the light's region
            mid = (lo + hi) >> 1
            right = dr.gather(Float, self.cell_cdf, mid, active) <= x
            lo = dr.select(right & (lo < hi), mid + 1, lo)
            hi = dr.select(~right & (lo < hi), mid, hi)
        c_hi = dr.gather(Float, self.cell_cdf, lo, active)
        c_lo = dr.select(lo > first, dr.gather(Float, self.cell_cdf, lo - 1, active & (lo > first)), 0.0)
        r = dr.clip((x - c_lo) / dr.maximum(c_hi - c_lo, 1e-12), 0.0, 1.0)
        cell = dr.gather(UInt32, self.cell_of, lo, active)
        row, col = cell // self.W, cell % self.W
        phi = (Float(col) + r) * (2 * np.pi / self.W)
        cos0, cos1 = dr.cos(Float(row) * (np.pi / self.H)), dr.cos(Float(row + 1) * (np.pi / self.H))
        cos_t = cos0 + u2.y * (cos1 - cos0)
        sin_t = dr.safe_sqrt(1 - cos_t * cos_t)
        return mi.Vector3f(sin_t * dr.sin(phi), cos_t, -sin_t * dr.cos(phi))

    def pdf(self, v, d, active=True):
        """Solid-angle density of :meth:`sample` for nearest vertices ``v`` at unit world directions ``d``."""
        import drjit as dr

        mi = self.mi
        u = dr.atan2(d.x, -d.z) * (1.0 / (2 * np.pi))
        u = u - dr.floor(u)
        t = dr.safe_acos(d.y) * (1.0 / np.pi)
        col = dr.minimum(mi.UInt32(u * self.W), self.W - 1)
        row = dr.minimum(mi.UInt32(t * self.H), self.H - 1)
        light = dr.gather(mi.UInt32, self.owner, row * self.W + col, active)
        p = dr.gather(mi.Float, self.prob, v * self.L + light, active)
        return p / dr.gather(mi.Float, self.area_dev, light, active)


class MaterialState:
    """Device arrays for evaluating the image-based material of one target (see module docstring).

    ``model``: :class:`~.model.Model`; ``target`` (T, 3); ``weights`` (T, S) per-vertex expression weights.
    """

    def __init__(self, model, target: np.ndarray, weights: np.ndarray, max_slots: int = 4, neighbourhoods=None,
                 light_basis: str = "voronoi", self_visibility: bool = True, method: str = "exact",
                 rank: int | None = None, depth_tolerance: float = None, visibility_rule: str = "cell",
                 visibility_grid: int = GRID_ORDER, near_occluders: float = 0.0, curved: int = 1,
                 visibility_weights=None):
        mi = ensure_variant()
        self.mi = mi
        self.model = model
        self.nb = neighbourhoods if neighbourhoods is not None else model.blend.nbhd
        S = len(model.expressions)
        self.K = min(max_slots, S)
        self.C = len(model.cameras)
        self.uploaded: list[int] = []
        self.triangles = to_jit(mi.UInt32, model.triangles.reshape(-1))
        self.n_triangles = len(model.triangles)
        self.sources = to_jit(mi.Float, np.asarray(model.vertices, np.float64).reshape(-1))
        self.visible = to_jit(mi.Float, np.asarray(model.visible, np.float32).reshape(-1))   # (S, C, T)
        self.visible_near = to_jit(mi.Float, np.asarray(model.visible_near, np.float32).reshape(-1))
        self.depth_tolerance = DEPTH_TOLERANCE if depth_tolerance is None else float(depth_tolerance)
        if not self.depth_tolerance > 0 or max_slots < 1:
            raise ValueError(f"depth_tolerance must be > 0 and max_slots >= 1 (got {depth_tolerance}, {max_slots})")
        self.cam_table = to_jit(mi.Float, np.concatenate([camera_params(c) for c in model.cameras]))
        self.n_lights = model.n_lights
        self.views = ViewSampler.from_cameras(model.cameras)
        self.light_basis = light_basis
        from .compression import compression_method

        compression_method(method)   # by name, as Renderer(method=, rank=): unknown names list the choices
        if method != "exact" and not rank:
            raise ValueError(f"compression method {method!r} needs a rank")
        self.method, self.rank = method, rank
        self.lights = LightInterpolator(model.light_directions, method=light_basis).to_device()
        self.self_visibility = self_visibility
        self.visibility_rule, self.visibility_grid = visibility_rule, int(visibility_grid)
        if self.visibility_grid < 0:
            raise ValueError(f"visibility_grid must be >= 0 (got {visibility_grid})")
        self._vis_sources: list[int] = []
        # metres: the skin within this distance of a hit does not shadow it (facerf_direct's shadow rays; 0: Mitsuba's)
        self.near_occluders = float(near_occluders)
        # the Phong level of the skin the scene traces (a facerf_face shape's): the surface the captured
        # self-visibility is traced on, so that it is what the shadow rays from a hit there let through
        from ..geometry.boubekeur2008 import check_curved

        self.curved = check_curved(curved)
        if not self.near_occluders >= 0:
            raise ValueError(f"near_occluders must be >= 0 metres (got {near_occluders})")
        if self.near_occluders > 0 and self_visibility and not self.visibility_grid:
            raise ValueError("near_occluders needs the triangle grid of self-visibility (visibility_grid > 0)")
        # (CELL_SAMPLES,) radiance along the cell samples (self_visibility.emitter_weights): each light's cell share
        # weighted by the environment's light in it, or None (unweighted: the share of the cell's solid angle)
        from .self_visibility import check_sample_weights

        self.visibility_weights = check_sample_weights(visibility_weights, rule=visibility_rule)
        if self.visibility_weights is not None and self_visibility and not self.visibility_grid:
            raise ValueError("visibility weights need the triangle grid of self-visibility (visibility_grid > 0)")
        if self_visibility and not self.visibility_grid:   # per vertex, interpolated (before 2026-12-02)
            from .self_visibility import visibility

            self.vis_light = to_jit(mi.Float, visibility(model, visibility_rule).reshape(-1))
        self._lum: dict[int, np.ndarray] = {}
        self._parts: dict[int, list[tuple]] = {}
        self.sampling = LightSampling(model.light_directions)
        self.update(target, weights)

    def update(self, target: np.ndarray, weights: np.ndarray) -> None:
        """A new target (T, 3) and per-vertex weights (T, S): the per-vertex tables change values, not sizes,
        so the material's kernels are re-used; a source not used before has its fields uploaded."""
        from ..blending import local_rotations

        mi, model = self.mi, self.model
        T, S = model.n_vertices, len(model.expressions)
        W = np.asarray(weights, np.float64)
        if W.shape != (T, S) or np.asarray(target).shape != (T, 3):
            raise ValueError(f"target {np.asarray(target).shape} / weights {W.shape} do not match the model "
                             f"({T} vertices, {S} expressions)")
        order = np.argsort(-W, axis=1, kind="stable")[:, :self.K]
        sw = np.take_along_axis(W, order, axis=1)
        sw = np.where(sw > 1e-6, sw, 0.0)
        sw /= np.maximum(sw.sum(1, keepdims=True), 1e-300)
        used = sorted(set(order[sw > 0].tolist()))
        self.used = used
        target = np.asarray(target, np.float64)
        rot = np.broadcast_to(np.eye(3), (T, self.K, 3, 3)).copy()  # identity for unused slots
        for s in used:
            R = local_rotations(target, model.vertices[s], self.nb)
            hit = (order == s) & (sw > 0)
            rot[hit] = R[np.nonzero(hit)[0]]
        self.target = to_jit(mi.Float, target.reshape(-1))
        self.slot_u = to_jit(mi.UInt32, np.where(sw > 0, order, 0).reshape(-1))
        self.slot_w = to_jit(mi.Float, sw.reshape(-1))
        self.slot_R = to_jit(mi.Float, rot.reshape(-1))
        if not set(used) <= set(self.uploaded):
            self._upload(sorted(set(self.uploaded) | set(used)))
        if self.self_visibility and self.visibility_grid and not set(used) <= set(self._vis_sources):
            self._upload_visibility(sorted(set(self._vis_sources) | set(used)))
        table = np.zeros((T, self.n_lights))
        for k in range(self.K):   # the slots' response per light, blended by the slots' weights
            for s in used:
                sel = (order[:, k] == s) & (sw[:, k] > 0)
                if s in self._lum:
                    table[sel] += sw[sel, k, None] * self._lum[s][sel]
        self.sampling.set_table(table)

    def _upload(self, sources: list[int]) -> None:
        """Fields of ``sources`` (every camera) on the device: float16 rows and per-field texel-index images.
        Each source's fields are read once (:meth:`_source_parts`); a source added later re-concatenates
        the parts already read, it does not read them again."""
        import drjit as dr

        from ..jitarrays import aligned_empty

        mi, model, C = self.mi, self.model, self.C
        index_parts, rf_parts, depth_parts, outline_parts = [], [], [], []
        offsets = np.zeros(len(model.expressions) * C, np.uint32)
        img_off, row_off = 0, 0
        for s in sources:
            for c, (local, rows, depth, outline) in enumerate(self._source_parts(s)):
                if rows is not None:
                    index_parts.append(np.where(local >= 0, local + row_off, -1).astype(np.int32))
                    rf_parts.append(rows)
                    depth_parts.append(depth)
                    outline_parts.append(outline)
                    row_off += len(rows)
                else:
                    index_parts.append(local)
                offsets[s * C + c] = img_off
                img_off += len(local)
        if row_off >= 2 ** 31 // (model.n_lights * 3):
            raise ValueError("too many texels for one material state; render fewer expressions at once")
        self.texel_index = to_jit(mi.Int32, np.concatenate(index_parts))
        self.field_offset = to_jit(mi.UInt32, offsets)
        if rf_parts:   # concatenated straight into the aligned buffer Dr.Jit reads (one copy of the rows, not two)
            rf = aligned_empty((row_off, model.n_lights, 3), np.float16)
            np.concatenate(rf_parts, out=rf)
            self.rf = dr.float16_array_t(mi.Float)(rf.reshape(-1))
        else:
            self.rf = to_device_f16(np.zeros((1, model.n_lights, 3)))
        self.texel_depth = to_jit(mi.Float, np.concatenate(depth_parts) if depth_parts else np.zeros(1, np.float32))
        self.texel_outline = to_jit(mi.Float, np.concatenate(outline_parts) if outline_parts else np.zeros(1, np.float32))
        self.uploaded = list(sources)

    def _source_parts(self, s: int) -> list[tuple]:
        """Per camera of source ``s``: (texel index image (H*W,) int32, −1 where no texel; rows (N, L, 3)
        float16 or None without a field; depth (N,) float32; outline (N,) float32), read once and kept (the
        exact rows are the memory-mapped field itself), and the source's blended response per light
        (``_lum[s]`` (T, L): each texel's mean over colours spread to its triangle's vertices by barycentrics,
        summed over cameras) for :class:`LightSampling`."""
        parts = self._parts.get(s)
        if parts is not None:
            return parts
        from scipy.sparse import csr_matrix

        model = self.model
        parts, lum_total = [], np.zeros((model.n_vertices, model.n_lights))
        for c in range(self.C):
            cam = model.cameras[c]
            local = np.full(cam.height * cam.width, -1, np.int32)
            if not model.has_field(s, c):
                parts.append((local, None, None, None))
                continue
            f = model.field(s, c)
            local[f.pixels[:, 0] * cam.width + f.pixels[:, 1]] = np.arange(len(f), dtype=np.int32)
            rows = self._rows(f, s, c)
            n = len(f)
            spread = csr_matrix((np.asarray(f.bary, np.float64).reshape(-1),
                                 (np.repeat(np.arange(n), 3), model.triangles[f.tri].reshape(-1))),
                                shape=(n, model.n_vertices))
            lum_total += spread.T @ np.asarray(rows, np.float32).mean(axis=2)             # (T, L)
            # texels on the subject's outline: read as the exact path reads them (frame.outline_texels)
            outline = outline_texels(f.depth_map())[f.pixels[:, 0], f.pixels[:, 1]].astype(np.float32)
            parts.append((local, rows, np.asarray(f.depth, np.float32), outline))
        self._lum[s] = lum_total
        self._parts[s] = parts
        return parts

    def _upload_visibility(self, sources: list[int]) -> None:
        """The per-triangle grids of captured self-visibility (:func:`.self_visibility.source_triangle_visibility`)
        of ``sources`` on the device, and each source's first row (``vis_base``, in triangles)."""
        from .self_visibility import source_triangle_visibility

        mi, model = self.mi, self.model
        grids = [source_triangle_visibility(model, s, self.visibility_rule, self.visibility_grid, self.near_occluders,
                                            self.curved, weights=self.visibility_weights) for s in sources]
        base = np.zeros(len(model.expressions), np.uint32)
        for k, s in enumerate(sources):
            base[s] = k * self.n_triangles
        self.vis_grid = to_jit(mi.Float, np.concatenate(grids).reshape(-1))
        self.vis_base = to_jit(mi.UInt32, base)
        self._vis_sources = list(sources)

    def _grid_corners(self, b):
        """The visibility grid's corners round barycentrics ``b`` and their weights (linear inside the grid's
        small triangle; :func:`.self_visibility.grid_barycentrics`): ([3 UInt32 rows], [3 Float weights])."""
        import drjit as dr

        from .self_visibility import GRID_INSET

        mi = self.mi
        k = self.visibility_grid
        x = dr.clip((b[0] - GRID_INSET / 3) * (k / (1 - GRID_INSET)), 0.0, float(k))
        y = dr.clip((b[1] - GRID_INSET / 3) * (k / (1 - GRID_INSET)), 0.0, float(k))
        y = dr.minimum(y, k - x)
        i = dr.minimum(mi.UInt32(dr.floor(x)), k)
        j = dr.minimum(mi.UInt32(dr.floor(y)), k)
        over = (i + j) > (k - 1)            # on the far edge: step back into the grid
        i = dr.select(over & (i > 0), i - 1, i)
        j = dr.select(over & ~(i > 0) & (j > 0) & ((i + j) > (k - 1)), j - 1, j)
        fx, fy = x - mi.Float(i), y - mi.Float(j)
        upper = (fx + fy) > 1
        k1 = k + 1
        c0 = dr.select(upper, (i + 1) * k1 + j + 1, i * k1 + j)
        c1 = dr.select(upper, i * k1 + j + 1, (i + 1) * k1 + j)
        c2 = dr.select(upper, (i + 1) * k1 + j, i * k1 + j + 1)
        w0 = dr.select(upper, fx + fy - 1, 1 - fx - fy)
        w1 = dr.select(upper, 1 - fx, fx)
        w2 = dr.select(upper, 1 - fy, fy)
        return [c0, c1, c2], [w0, w1, w2]

    def _rows(self, f, s: int, c: int) -> np.ndarray:
        """(N, L, 3) reflectance rows of field (s, c) under this state's compression method: the stored field,
        or (``pca``) reconstructed at upload from the model's ``<method><rank>`` file (device memory is then
        that of the exact rows; the stored coefficients are what is read)."""
        if self.method == "exact":
            return np.asarray(f.rf)
        from .compression import reconstruct

        return reconstruct(self.model.compressed_field(s, c, self.rank, self.method), self.model.light_directions)

    # ------------------------------------------------------------------ kernel
    def evaluate(self, tri, p, view, light, active=True, bary=None):
        """Radiance per unit irradiance (Color3f) for hits (triangle ``tri``, point ``p``), unit world
        directions ``view`` (towards the viewer) and ``light`` (towards the light). ``bary``: the hits'
        barycentrics in ``tri`` ([3 Float]) where the caller has them (a hit on a finer surface over the
        target, e.g. ``facerf_face``'s Phong sub-faces); else they are those of ``p`` in the target triangle.

        Texels are chosen as the exact path chooses them (:meth:`.frame.LitFrame.shade`): per camera the 2x2
        bilinear taps whose seen surface lies within :data:`DEPTH_TOLERANCE` of the hit (a texel at camera
        ``c``'s silhouette that shows another part of the surface is not used), in three tiers — cameras
        that see the vertex or a triangle round it (``visible_near``), cameras that see the vertex itself
        (``visible``), and the latter without the depth test — the first tier with any weight wins."""
        import drjit as dr

        mi = self.mi
        Float, UInt32, Int32 = mi.Float, mi.UInt32, mi.Int32
        active = mi.Bool(active)
        active &= mi.UInt32(tri) < self.n_triangles
        tri = dr.select(active, mi.UInt32(tri), 0)   # a part's triangle (index past the skin's) is never read
        b = barycentric(self.triangles, self.target, tri, p) if bary is None else list(bary)
        vid = [dr.gather(UInt32, self.triangles, tri * 3 + k, active) for k in range(3)]
        n = dr.width(tri) if dr.width(tri) > 1 else dr.width(p.x)
        K, C, T, L3 = self.K, self.C, len(self.model.vertices[0]), self.n_lights * 3
        n_pairs = dr.opaque(UInt32, 3 * K)
        tol = dr.opaque(Float, self.depth_tolerance)
        if self.self_visibility and self.visibility_grid:
            corners, corner_w = self._grid_corners(b)
            G = (self.visibility_grid + 1) ** 2

        def cond(i, *_):
            return i < n_pairs

        def body(i, *acc):
            k = i // K
            j = i - k * K
            v = dr.select(k == 0, vid[0], dr.select(k == 1, vid[1], vid[2]))
            bk = dr.select(k == 0, b[0], dr.select(k == 1, b[1], b[2]))
            slot = v * K + j
            w = dr.gather(Float, self.slot_w, slot, active)
            u = dr.gather(UInt32, self.slot_u, slot, active)
            R = [dr.gather(Float, self.slot_R, slot * 9 + e, active) for e in range(9)]

            def rotate(x):
                return mi.Vector3f(R[0] * x.x + R[1] * x.y + R[2] * x.z, R[3] * x.x + R[4] * x.y + R[5] * x.z,
                                   R[6] * x.x + R[7] * x.y + R[8] * x.z)

            use = active & (w > 0)
            cam_ids, cam_w = self.views.weights_jit(rotate(view))
            light_ids, light_w = self.lights.weights_jit(rotate(light), use)
            cam_w = [dr.select(use, x, 0.0) for x in cam_w]  # keep NaN from inactive lanes out of sums
            light_w = [dr.select(use, x, 0.0) for x in light_w]
            if self.self_visibility:   # the captured self-visibility of each light, divided out (with the fill)
                if self.visibility_grid:
                    row0 = (dr.gather(UInt32, self.vis_base, u, use) + tri) * G
                for li in range(3):
                    sv = Float(0)
                    for kk in range(3):
                        if self.visibility_grid:   # the source's grid inside the triangle, at the hit's barycentrics
                            sv += corner_w[kk] * dr.gather(Float, self.vis_grid, (row0 + corners[kk]) * self.n_lights
                                                           + light_ids[li], use)
                        else:
                            sv += b[kk] * dr.gather(Float, self.vis_light, (u * T + vid[kk]) * self.n_lights
                                                    + light_ids[li], use)
                    light_w[li] = light_w[li] * dr.select(sv >= MIN_VISIBILITY, dr.rcp(sv), 1.0)
            ps = [Float(0), Float(0), Float(0)]
            for kk in range(3):
                for d in range(3):
                    ps[d] += b[kk] * dr.gather(Float, self.sources, (u * T + vid[kk]) * 3 + d, use)
            # per tier, the cameras that see the vertex (near / itself) in this source, renormalised
            tiers = []
            for table in (self.visible_near, self.visible):
                cw = [cam_w[m] * dr.gather(Float, table, (u * C + cam_ids[m]) * T + v, use) for m in range(3)]
                ctot = cw[0] + cw[1] + cw[2]
                cinv = dr.select(ctot > 0, dr.rcp(ctot), 0.0)
                tiers.append([x * cinv for x in cw])
            acc = list(acc)
            for m in range(3):
                c = cam_ids[m]
                wp, wf = tiers[0][m], tiers[1][m]
                usec = use & ((wp > 0) | (wf > 0))

                def P(e):
                    return dr.gather(Float, self.cam_table, c * CAM_PARAMS + e, usec)

                uu, vv, dist, zc, wi, hi = project(P, ps)
                foff = dr.gather(UInt32, self.field_offset, u * C + c, usec)
                col = [Float(0), Float(0), Float(0)]
                col_d = [Float(0), Float(0), Float(0)]
                col_i = [Float(0), Float(0), Float(0)]
                col_di = [Float(0), Float(0), Float(0)]
                cov, cov_d, cov_i, cov_di = Float(0), Float(0), Float(0), Float(0)
                for pix, wgt, inside in bilinear_taps(uu, vv, wi, hi, usec & (zc > 0)):
                    t = dr.gather(Int32, self.texel_index, foff + pix, inside)
                    ok = inside & (t >= 0)
                    tw = dr.select(ok, wgt, 0.0)
                    tsel = UInt32(dr.select(ok, t, 0))
                    seen = ok & (dr.abs(dr.gather(Float, self.texel_depth, tsel, ok) - dist) <= tol)
                    tw_d = dr.select(seen, wgt, 0.0)
                    off_outline = 1.0 - dr.gather(Float, self.texel_outline, tsel, ok)
                    row = tsel * L3
                    for ch in range(3):
                        val = Float(0)
                        for li in range(3):
                            val += light_w[li] * Float(dr.gather(type(self.rf), self.rf,
                                                                 row + light_ids[li] * 3 + ch, ok))
                        col[ch] += tw * val
                        col_d[ch] += tw_d * val
                        col_i[ch] += tw * off_outline * val
                        col_di[ch] += tw_d * off_outline * val
                    cov += tw
                    cov_d += tw_d
                    cov_i += tw * off_outline
                    cov_di += tw_d * off_outline
                seen = usec & (cov_d > 1e-3)
                good = usec & (cov > 1e-3)
                # as LitFrame.shade: the texels off the outline where the camera has any for the point, and a
                # camera that sees it only through outline texels weighs OUTLINE_WEIGHT
                inner_d, inner = cov_di > 1e-3, cov_i > 1e-3
                sel_d = [dr.select(inner_d, col_di[ch] * dr.rcp(cov_di), col_d[ch] * dr.select(seen, dr.rcp(cov_d), 0.0))
                         for ch in range(3)]
                sel = [dr.select(inner, col_i[ch] * dr.rcp(cov_i), col[ch] * dr.select(good, dr.rcp(cov), 0.0))
                       for ch in range(3)]
                low = dr.opaque(Float, OUTLINE_WEIGHT)
                kd, ka = dr.select(inner_d, 1.0, low), dr.select(inner, 1.0, low)
                # accumulators: (near cameras, depth-tested), (own cameras, depth-tested), (own, any texel)
                for t_, (wt, cc) in enumerate(((dr.select(seen, bk * w * wp * kd, 0.0), sel_d),
                                               (dr.select(seen, bk * w * wf * kd, 0.0), sel_d),
                                               (dr.select(good, bk * w * wf * ka, 0.0), sel))):
                    for ch in range(3):
                        acc[4 * t_ + ch] = acc[4 * t_ + ch] + wt * cc[ch]
                    acc[4 * t_ + 3] = acc[4 * t_ + 3] + wt
            return (i + 1, *acc)

        zeros = [dr.opaque(Float, 0, n) for _ in range(12)]
        acc = dr.while_loop((dr.opaque(UInt32, 0, n), *zeros), cond, body)[1:]
        primary, fallback = acc[3] > 1e-9, acc[7] > 1e-9
        pick = [dr.select(primary, acc[q], dr.select(fallback, acc[4 + q], acc[8 + q])) for q in range(4)]
        inv = dr.select(pick[3] > 1e-9, dr.rcp(pick[3]), 0.0)
        return mi.Color3f(pick[0] * inv, pick[1] * inv, pick[2] * inv)

    def nearest_vertex(self, tri, p=None, bary=None, active=True):
        """The target vertex (UInt32) nearest to each hit (the largest barycentric of its triangle): hits as
        (triangle ``tri``, point ``p``) or (``tri``, barycentrics ``bary``)."""
        import drjit as dr

        mi = self.mi
        active = mi.Bool(active) & (mi.UInt32(tri) < self.n_triangles)   # a part's triangle: none of the skin's
        tri = dr.select(active, mi.UInt32(tri), 0)
        b = barycentric(self.triangles, self.target, tri, p) if bary is None else bary
        k = dr.select((b[0] >= b[1]) & (b[0] >= b[2]), 0, dr.select(b[1] >= b[2], 1, 2))
        return dr.gather(mi.UInt32, self.triangles, tri * 3 + mi.UInt32(k), active)
