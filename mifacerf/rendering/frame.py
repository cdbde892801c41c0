"""A lit frame: everything needed to shade hits on the target face, as Dr.Jit arrays.

:class:`LitFrame` holds, for every render chunk (source expression ``s``, capture
camera ``c``) of a frame, the chunk's lit image in camera ``c``'s pixels (RGB +
coverage, from :func:`.relight.lit_texels`), its texel depth map, its per-vertex
weights, the source geometry and camera ``c``'s calibration — all concatenated so
that :meth:`LitFrame.shade` is one Dr.Jit kernel with a symbolic loop over chunks,
the same compiled code for any frame. The Python API renderer and the Mitsuba
integrator plugin both call :meth:`LitFrame.shade`.

Shading a hit (triangle ``tri``, barycentrics ``b`` on the *target* mesh): for each
chunk, ``p_s = Σ_k b_k V_s[tri_k]`` (the same surface point in the source
geometry), projected into camera ``c`` with its lens distortion; the lit image is
read there bilinearly (colour / coverage) from those of the 2x2 texels whose seen
surface lies within ``depth_tolerance`` of ``p_s``'s distance (occlusion-aware
filtering: a texel showing an occluder, or a surface behind a silhouette, is not
used; on a surface camera ``c`` sees obliquely the tolerance grows with the depth's slope there,
:func:`grazing_tolerance`); a texel camera ``c`` sees more obliquely than ``MIN_VIEW_COS`` is not read
where the render view sees the point at least twice as squarely (``OBLIQUE_RATIO``; the renderer sets
``LitFrame.view_origin``, the integrator plugin does not: rule off — there a hit the rule leaves uncovered
would be a hole, the renderer's image-space fill being out of reach of a per-sample integrator; measured
with it on, docs/rendering.md "The scene loop's frame"); the chunk's weight is ``a = Σ_k b_k a_{tri_k}`` in each of the plan's two tiers
(:mod:`.chunks`: primary, fallback). Result: Σ a·colour / Σ a over the chunks that see
the point, with the primary weights; where no primary chunk sees it, with the fallback
weights; where no chunk sees it, over the chunks regardless of the depth test with the
fallback weights (documented fall-back); where no chunk covers the point at all,
``covered`` is False. A field's texels on the subject's outline in its camera (:func:`outline_texels`:
their pixels mix the surface with the capture's dark backdrop) are read only where the chunk has no
other texel for the point, and such a chunk weighs ``OUTLINE_WEIGHT`` of its weight: a point there takes
the colour of the texels inside or of the chunks that see it off their outline, so a composite shows no
dark fringe, and nothing covered before loses its coverage.

A frame's pixels (:func:`resolve_pixels`): the alpha is the share of a pixel's samples that hit the
target geometry (skin, extensions, eyes, teeth), so the silhouette is the geometry's anti-aliased outline
whatever the fields cover; the colour is the mean of the pixel's covered samples, and a pixel whose hits
have no field coverage at all takes the mean colour of the nearest pixel in the image that has some
(documented fall-back: no holes where a surface no field sees is hit, no matte editing in a composite).
"""
from __future__ import annotations

import numpy as np

from ..jitarrays import to_jit
from .jitgeom import CAM_PARAMS, bilinear_taps, camera_params, project
from ..variant import ensure_variant

#: the fill's smoothing (Gaussian sigma, a fraction of the image's larger side; :func:`resolve_pixels`)
FILL_SIGMA = 1.0 / 32


def resolve_pixels(pix: np.ndarray, colour: np.ndarray, covered: np.ndarray, height: int, width: int,
                   spp: int, window: bool = True) -> tuple[np.ndarray, int]:
    """Box-filter a frame's hit samples into (H, W, 4) float32 linear RGB premultiplied by alpha.

    ``pix`` (N,): the pixel (row-major index) of each sample that hit the target geometry; ``colour``
    (N, 3) its shaded colour, used where ``covered`` (N,) bool (some field saw the point). Alpha: hits /
    ``spp``, the geometry's coverage of the pixel. RGB: alpha times the mean of the pixel's covered
    samples — a pixel whose samples are all covered gets exactly Σ colour / ``spp``; a pixel with hits
    but no covered sample takes the covered pixels' mean colours smoothed over the gap (a normalised
    Gaussian of sigma ``FILL_SIGMA`` × the image's larger side; where none lies that near, the nearest
    pixel's, Euclidean in the image); with no covered sample in the whole frame, black. Returns (image,
    pixels filled that way). An unseen surface (the back of the neck beyond the outermost camera) so
    takes the low frequencies of what surrounds it, not streaks of its neighbours' colours. ``window``: the
    smoothing runs over the gap's bounding box grown by the filter's radius only (the same values bit for
    bit, tests/evaluation/test_silhouette.py; False: over the whole image, as before 2026-12-03).
    """
    n = height * width
    pix = np.asarray(pix, np.int64)
    covered = np.asarray(covered, bool)
    hits = np.bincount(pix, minlength=n).astype(np.float64)
    count = np.bincount(pix, weights=covered.astype(np.float64), minlength=n)
    total = np.stack([np.bincount(pix, weights=np.where(covered, colour[:, ch], 0.0), minlength=n)
                      for ch in range(3)], axis=-1)
    mean = total / np.maximum(count, 1.0)[:, None]
    empty = (hits > 0) & (count == 0)
    filled = 0
    if empty.any() and (count > 0).any():
        fill = np.zeros((int(empty.sum()), 3))
        far = np.ones(len(fill), bool)    # gap pixels the smoothing does not reach: the nearest pixel's colour
        sigma = FILL_SIGMA * max(height, width)
        if sigma > 0:       # the covered pixels' colours smoothed over the gap (normalised convolution)
            from scipy.ndimage import gaussian_filter

            # only over the gap's bounding box grown by the filter's radius (scipy's: truncate 4 sigma): the
            # filtered values at the gap read nothing outside it, so they are those of the whole image, bit
            # for bit, for a fraction of the cost (four filters of a 1024² image took 0.7 s for a few pixels)
            radius = int(4.0 * sigma + 0.5)
            rows, cols = np.divmod(np.flatnonzero(empty), width)
            win = (slice(max(rows.min() - radius, 0), min(rows.max() + radius + 1, height)),
                   slice(max(cols.min() - radius, 0), min(cols.max() + radius + 1, width))) if window else \
                (slice(0, height), slice(0, width))
            at = (rows - win[0].start, cols - win[1].start)
            have = (count > 0).reshape(height, width)
            wsum = gaussian_filter(have[win].astype(np.float64), sigma, mode="constant")[at]
            smooth = np.stack([gaussian_filter(np.where(have, mean[:, ch].reshape(height, width), 0.0)[win], sigma,
                                               mode="constant")[at] for ch in range(3)], -1)
            far = ~(wsum > 1e-3)
            fill[~far] = smooth[~far] / np.maximum(wsum[~far], 1e-30)[:, None]
        if far.any():       # the distance transform only where it is read (0.08 s at 1024², on every gap before)
            from scipy.ndimage import distance_transform_edt

            _, (ii, jj) = distance_transform_edt((count == 0).reshape(height, width), return_indices=True)
            nearest = (ii * width + jj).reshape(-1)
            fill[far] = mean[nearest[np.flatnonzero(empty)[far]]]
        mean[empty] = fill
        filled = int(empty.sum())
    rgba = np.empty((n, 4))
    rgba[:, :3] = (total + (hits - count)[:, None] * mean) / spp
    rgba[:, 3] = hits / spp
    return rgba.reshape(height, width, 4).astype(np.float32), filled


#: the traced face vertices' outward offset, in units of their umbrella depth (:class:`ChordOffset`)
CHORD_OFFSET = 0.25


class ChordOffset:
    """The target mesh a frame traces (its alpha and hits): each vertex of the face moved out along its
    normal by ``k`` × its umbrella depth (how far the mean of its neighbours lies below it, convex only).

    The template's mesh interpolates the skin at its vertices, so on a convex stretch (the nose's tip and
    dorsum, the chin, the jaw line) every chord between them lies inside the skin — by about a quarter of
    the umbrella depth at an edge's middle — and the render's outline is inside the subject's (the 30°
    view's nose tip was cut by 3-5 mm; the truth's own template vertices cut it the same way). Moved out
    by that much, the traced edges lie on the skin on average. Vertices on the mesh's border (the neck cut,
    the eye and mouth openings: the lids' and lips' margins) and the ``fixed`` ones (the extensions, whose
    outline is fitted to the capture's by registration) stay. A hit is shaded at its triangle and
    barycentrics on the source geometry the fields were built on (the offset, under a millimetre, shifts
    an oblique hit by offset × tan(angle); re-meeting each ray on the untraced triangle gained 0.1 dB of
    face PSNR on captured views for 20 ms a 256² frame: not taken)."""

    def __init__(self, triangles, n_vertices: int, fixed=None, k: float = CHORD_OFFSET):
        F = np.asarray(triangles, np.int64)
        self.F, self.k = F, float(k)
        e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        edges, count = np.unique(e, axis=0, return_counts=True)
        self.a, self.b = edges[:, 0], edges[:, 1]
        self.degree = np.bincount(edges.reshape(-1), minlength=n_vertices).astype(np.float64)
        movable = self.degree > 0
        movable[edges[count == 1].reshape(-1)] = False
        if fixed is not None and len(fixed):
            movable[np.asarray(fixed, np.int64)] = False
        self.movable = movable

    def __call__(self, V: np.ndarray) -> np.ndarray:
        from ..geometry.visibility import vertex_normals

        V = np.asarray(V, np.float64)
        if self.k == 0 or not self.movable.any() or V.shape != (len(self.degree), 3) or not np.isfinite(V).all():
            return V                     # (not a frame's input: the renderer's checks say what is wrong)
        s = np.zeros_like(V)
        np.add.at(s, self.a, V[self.b])
        np.add.at(s, self.b, V[self.a])
        N = vertex_normals(V, self.F)
        lap = s / np.maximum(self.degree, 1.0)[:, None] - V
        depth = np.where(self.movable, np.maximum(-np.einsum("td,td->t", lap, N), 0.0), 0.0)
        return V + (self.k * depth)[:, None] * N


def traced_offset(model, curved: int) -> ChordOffset:
    """The :class:`ChordOffset` a frame of ``model`` traces on surface ``curved`` (a Phong level): a whole-head
    template's face vertices moved out by the chords' sag when flat (its extensions fixed); the identity on
    the Phong surface, or for a face-only template, which traces its registered mesh as it is."""
    exts = model.template.get("extensions") or {}
    ext = [v for e in exts.values() for v in e.get("vertices", [])]
    k = CHORD_OFFSET if exts and curved == 1 else 0.0
    return ChordOffset(model.triangles, model.n_vertices, fixed=ext, k=k)


def facing_weights(expression_weights: np.ndarray, target: np.ndarray, triangles: np.ndarray, centre) -> np.ndarray:
    """A frame's (T, S) expression weights with the rows of vertices the camera at ``centre`` cannot show set to
    0: vertices of no target triangle that faces the camera (a render's trace passes back faces, so every hit
    is on a facing triangle, and all three of its vertices keep their rows). The frame then plans, lights and
    relights only the half of the head it shows (the extensions doubled the template with the back of the
    head); a hit's weights, rotations and lighting are those of before."""
    V = np.asarray(target, np.float64)
    F = np.asarray(triangles, np.int64)
    W = np.asarray(expression_weights)
    if V.ndim != 2 or V.shape[1:] != (3,) or W.ndim != 2 or len(W) != len(V) or not len(F) or F.max() >= len(V) \
            or not np.isfinite(V).all():
        return W                     # not a frame's input: plan_frame says what is wrong
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    facing = np.einsum("fd,fd->f", n, np.asarray(centre, np.float64) - V[F[:, 0]]) > 0
    keep = np.ones(len(V), bool)
    keep[F.reshape(-1)] = False
    keep[F[facing].reshape(-1)] = True
    return W if keep.all() else np.where(keep[:, None], W, 0.0)


def outline_texels(depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: the texels of a field (finite ``depth`` (H, W), +inf where it has none) on the subject's
    outline in its camera — a 4-neighbour pixel shows the background: no texel, in a piece of the texel-free
    area that reaches the image's border (the eye and mouth openings, enclosed by the face, are not
    background). Such a pixel mixed the surface with the stage's dark backdrop (partial coverage): read
    from it, the surface shows a dark fringe once composited over a plate."""
    from scipy.ndimage import binary_dilation, label

    seen = np.isfinite(np.asarray(depth))
    if not seen.any() or seen.all():
        return np.zeros(seen.shape, bool)
    pieces, _ = label(~seen)
    border = np.unique(np.concatenate([pieces[0], pieces[-1], pieces[:, 0], pieces[:, -1]]))
    return seen & binary_dilation(np.isin(pieces, border[border > 0]))


_OUTLINES: dict = {}


def _cached_outline(depth: np.ndarray) -> np.ndarray:
    """:func:`outline_texels` of a field's depth map, remembered by the map's content (a field's depth map is
    the same every frame; the labelling costs a few ms a chunk, the key 0.5 ms)."""
    import hashlib

    d = np.ascontiguousarray(depth, np.float32)
    key = (d.shape, hashlib.sha1(d.tobytes()).digest())
    ids = _OUTLINES.get(key)
    if ids is None:
        if len(_OUTLINES) >= 2048:
            _OUTLINES.pop(next(iter(_OUTLINES)))
        ids = _OUTLINES[key] = np.flatnonzero(outline_texels(d)).astype(np.int32)
    edge = np.zeros(d.shape, bool)
    edge.reshape(-1)[ids] = True
    return edge


#: the relative weight of a render chunk that sees a point only through texels on the outline
OUTLINE_WEIGHT = 1e-3


def mark_outline(image: np.ndarray, depth: np.ndarray, mark: bool = True) -> np.ndarray:
    """A chunk's lit image (H, W, 4) float32 with its :func:`outline_texels` marked: coverage −1 instead
    of 1 (:meth:`LitFrame.shade` reads such a texel only where the chunk has no other texel for the point,
    so nothing that was covered loses its coverage); ``mark=False``: unchanged."""
    image = np.asarray(image, np.float32)
    if not mark:
        return image
    edge = _cached_outline(depth)
    if not edge.any():
        return image
    out = image.copy()
    out[edge, 3] = -np.abs(out[edge, 3])
    return out


#: the depth test's allowance for a surface seen obliquely, in pixels of depth slope (:func:`grazing_tolerance`)
GRAZING_SLACK = 1.5
#: ... and its cap, in depth tolerances
GRAZING_CAP = 4.0
#: a chunk reads no texel of a point its camera sees more obliquely than this (|cos| of the angle between
#: the view ray and the source triangle's normal): a texel seen edge-on holds the grazing highlight of that
#: camera's view (the sky's reflection, bright streaks) or a shadowed sliver (black), not the surface a
#: view from elsewhere sees; a point no other chunk sees is filled (:func:`resolve_pixels`)
MIN_VIEW_COS = 0.3
#: ... when the render view sees the point at least 1 / OBLIQUE_RATIO times as squarely (a render from the
#: capture camera itself keeps every texel it saw)
OBLIQUE_RATIO = 0.5


def view_cosine(P, p, q):
    """|cos| of the angle between the view ray of the camera whose table row ``P`` gives to the point ``p``
    (three Floats) and the normal of its source triangle ``q`` (three vertices of three Floats)."""
    centre = [-(P(j) * P(9) + P(3 + j) * P(10) + P(6 + j) * P(11)) for j in range(3)]   # -R^T t
    return cosine_to(centre, p, q)


def cosine_to(centre, p, q):
    """|cos| of the angle between the ray from ``centre`` to ``p`` and the normal of the triangle ``q``."""
    import drjit as dr

    e1 = [q[1][d] - q[0][d] for d in range(3)]
    e2 = [q[2][d] - q[0][d] for d in range(3)]
    n = [e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0]]
    ray = [p[d] - centre[d] for d in range(3)]
    dot = n[0] * ray[0] + n[1] * ray[1] + n[2] * ray[2]
    norms = dr.sqrt((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]) * (ray[0] * ray[0] + ray[1] * ray[1] + ray[2] * ray[2]))
    return dr.minimum(dr.abs(dot) * dr.rcp(dr.maximum(norms, 1e-30)), 1.0)


def grazing_tolerance(P, cos, dist, tol, slack):
    """The depth tolerance at a point ``p`` (three Floats) of the source triangle ``q`` (three vertices of three
    Floats) seen by the camera whose table row ``P`` gives, at ``dist`` from its centre: ``tol`` plus ``slack``
    pixels of the surface's depth slope in that camera (a pixel's footprint ``dist / f`` times the tangent of
    the angle between the view ray and the triangle's normal), at most ``GRAZING_CAP`` × ``tol`` more. A
    field's texel holds the depth at its centre; the bilinear taps lie up to a pixel from the point, so on a
    surface seen edge-on (the back of the neck in the outermost camera) the depths of the very surface
    differ by more than ``tol`` and the point fell to the no-depth-test tier, reading whatever those texels
    show. (NumPy twin: :func:`grazing_tolerance_np`.)"""
    import drjit as dr

    tan = dr.sqrt(dr.maximum(1.0 - cos * cos, 0.0)) * dr.rcp(dr.maximum(cos, 1e-3))
    return tol + dr.minimum(slack * dist * dr.rcp(P(12)) * tan, GRAZING_CAP * tol)


def view_cosine_np(camera, p, q) -> np.ndarray:
    """:func:`view_cosine` in NumPy: ``p`` (N, 3) points of the triangles ``q`` (N, 3, 3) in ``camera``."""
    n = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
    ray = p - camera.centre
    return np.minimum(np.abs((n * ray).sum(1)) / np.maximum(np.linalg.norm(n, axis=1) * np.linalg.norm(ray, axis=1),
                                                            1e-30), 1.0)


def grazing_tolerance_np(cos, dist, camera, tol: float, slack: float = GRAZING_SLACK) -> np.ndarray:
    """:func:`grazing_tolerance` in NumPy (``cos`` from :func:`view_cosine_np`, ``dist`` (N,))."""
    tan = np.sqrt(np.maximum(1.0 - cos * cos, 0.0)) / np.maximum(cos, 1e-3)
    return tol + np.minimum(slack * dist / camera.K[0, 0] * tan, GRAZING_CAP * tol)


class LitFrame:
    """The shading state of one frame. Built by :meth:`mifacerf.rendering.renderer.Renderer.light_frame`.

    ``target`` (T, 3) and ``triangles`` (F, 3): the target mesh; ``chunks``: list of
    dicts with keys ``s``, ``c``, ``weights`` (T,) and ``fallback`` (T,) (the two tiers'
    per-vertex weights; ``fallback`` defaults to ``weights``), ``image`` (H, W, 4) lit RGB + coverage,
    ``depth`` (H, W), ``camera`` (a :class:`~mifacerf.camera.Camera`); ``sources`` {s: (T, 3)}.
    ``images`` and ``depths``: the chunks' lit images (outline texels marked as :func:`mark_outline` does)
    and depth maps already on the device, flat Floats of H*W*4 and H*W per chunk in order (the renderer
    builds them there); the chunks then give ``shape`` (H, W) instead of ``image`` and ``depth``.
    """

    def __init__(self, target: np.ndarray, triangles: np.ndarray, chunks: list[dict], sources: dict,
                 depth_tolerance: float = 0.004, outline: bool = True, images=None, depths=None,
                 grazing_slack: float = GRAZING_SLACK, min_view_cos: float = MIN_VIEW_COS):
        mi = ensure_variant()
        self.mi = mi
        self.n_chunks = len(chunks)
        self.n_vertices = len(target)
        self.triangles_np = np.asarray(triangles, np.int64)
        self.target_np = np.asarray(target, np.float64)
        self.triangles = to_jit(mi.UInt32, self.triangles_np.reshape(-1))
        self.target = to_jit(mi.Float, self.target_np.reshape(-1))
        self.depth_tolerance = float(depth_tolerance)
        self.grazing_slack = float(grazing_slack)
        self.min_cos = float(min_view_cos)
        #: the render camera's centre (3,), set by the renderer for :data:`MIN_VIEW_COS`'s rule (None: no rule)
        self.view_origin = None
        src_ids = sorted(sources)
        src_offset = {s: i * len(target) * 3 for i, s in enumerate(src_ids)}
        self.sources = to_jit(mi.Float, np.concatenate([np.asarray(sources[s], np.float64).reshape(-1)
                                                        for s in src_ids]) if src_ids else np.zeros(3))
        img_parts, depth_parts, w_parts, f_parts, table = [], [], [], [], []
        img_off = 0
        for i, ch in enumerate(chunks):
            h, w = ch["shape"] if images is not None else ch["image"].shape[:2]
            if images is None:
                img_parts.append(mark_outline(ch["image"], ch["depth"], outline).reshape(-1))
                depth_parts.append(np.asarray(ch["depth"], np.float32).reshape(-1))
            w_parts.append(np.asarray(ch["weights"], np.float32))
            f_parts.append(np.asarray(ch.get("fallback", ch["weights"]), np.float32))
            row = np.zeros(CAM_PARAMS + 3)
            row[:CAM_PARAMS] = camera_params(ch["camera"])
            row[CAM_PARAMS] = img_off  # offset of the chunk's pixels (in pixels)
            row[CAM_PARAMS + 1] = src_offset[ch["s"]]
            row[CAM_PARAMS + 2] = i * len(target)
            table.append(row)
            img_off += h * w
        if img_off >= 2 ** 30:
            raise ValueError("frame too large: the lit images exceed 2^30 pixels")
        self.stride = CAM_PARAMS + 3
        self.table = to_jit(mi.Float, np.concatenate(table) if table else np.zeros(self.stride))
        self.images = images if images is not None else to_jit(mi.Float, np.concatenate(img_parts) if img_parts else np.zeros(4))
        self.depths = depths if depths is not None else to_jit(mi.Float, np.concatenate(depth_parts) if depth_parts else np.zeros(1))
        self.weights = to_jit(mi.Float, np.concatenate(w_parts) if w_parts else np.zeros(1))
        self.fallback = to_jit(mi.Float, np.concatenate(f_parts) if f_parts else np.zeros(1))
        # per target triangle, the chunks with a weight (either tier) at one of its vertices, in chunk order:
        # a sample loops over its triangle's only (any other chunk adds +0.0 there: the same sums bit for bit;
        # a drive frame's §5 weights touch ~128 chunks, a triangle ~10-20)
        live = np.stack([(w > 0) | (f > 0) for w, f in zip(w_parts, f_parts)], axis=1) if chunks else \
            np.zeros((len(target), 0), bool)
        per_tri = live[self.triangles_np].any(axis=1)                     # (F, chunks)
        self.chunk_start = to_jit(mi.UInt32, np.concatenate([[0], np.cumsum(per_tri.sum(1))]).astype(np.uint32))
        self.chunk_list = to_jit(mi.UInt32, np.append(np.nonzero(per_tri)[1], 0).astype(np.uint32))

    # ------------------------------------------------------------------ kernel
    def shade(self, tri, bary, active=True):
        """Shade hits: ``tri`` (UInt32), ``bary`` (Vector3f, b0 b1 b2) → (Color3f, covered, fell_back).

        ``covered``: some chunk saw the point; ``fell_back``: only without the depth test.

        A Dr.Jit function (traceable inside Mitsuba kernels): a symbolic loop over the chunks with a weight
        at the hit's triangle.
        """
        import drjit as dr

        mi = self.mi
        Float, UInt32, Int32 = mi.Float, mi.UInt32, mi.Int32
        active = mi.Bool(active)
        vid = [dr.gather(UInt32, self.triangles, tri * 3 + k, active) for k in range(3)]
        b = [bary.x, bary.y, bary.z]
        n = dr.width(tri)
        stride = self.stride
        tol = dr.opaque(Float, self.depth_tolerance)
        slack = dr.opaque(Float, self.grazing_slack)
        min_cos = dr.opaque(Float, self.min_cos)
        # how squarely the render view sees each hit (target triangle's normal): 0 = no oblique-texel rule
        cos_r = Float(0)
        if self.view_origin is not None:
            o = [dr.opaque(Float, float(x)) for x in np.asarray(self.view_origin, np.float64).reshape(3)]
            qt = [[dr.gather(Float, self.target, vid[k] * 3 + d, active) for d in range(3)] for k in range(3)]
            pt = [b[0] * qt[0][d] + b[1] * qt[1][d] + b[2] * qt[2][d] for d in range(3)]
            cos_r = cosine_to(o, pt, qt)
        first = dr.gather(UInt32, self.chunk_start, tri, active)
        last = dr.gather(UInt32, self.chunk_start, tri + 1, active)

        def cond(j, *_):
            return j < last

        def body(j, *acc):
            i = dr.gather(UInt32, self.chunk_list, j, active)
            base = i * stride

            def P(k):
                return dr.gather(Float, self.table, base + k, active)

            src = UInt32(P(CAM_PARAMS + 1))
            woff = UInt32(P(CAM_PARAMS + 2))
            ioff = UInt32(P(CAM_PARAMS))
            a = Float(0)
            af = Float(0)
            p = [Float(0), Float(0), Float(0)]
            q = [[dr.gather(Float, self.sources, src + vid[k] * 3 + d, active) for d in range(3)] for k in range(3)]
            for k in range(3):
                a += b[k] * dr.gather(Float, self.weights, woff + vid[k], active)
                af += b[k] * dr.gather(Float, self.fallback, woff + vid[k], active)
                for d in range(3):
                    p[d] += b[k] * q[k][d]
            u, v, dist, zc, wi, hi = project(P, p)
            use = active & ((a > 0) | (af > 0)) & (zc > 0)
            cos_v = view_cosine(P, p, q)
            tol_p = grazing_tolerance(P, cos_v, dist, tol, slack)
            use &= (cos_v >= min_cos) | (cos_v >= OBLIQUE_RATIO * cos_r)
            # bilinear over the 2x2 texels, each tap used only if the surface camera c saw there lies
            # at the point's distance (occlusion-aware filtering); the last resort ignores depth
            # each sum twice: over every texel, and over the texels off the outline (coverage > 0; an
            # outline texel, coverage -1, is read only where the chunk has no other texel for the point)
            col_d, col_di = [Float(0), Float(0), Float(0)], [Float(0), Float(0), Float(0)]
            col, col_i = [Float(0), Float(0), Float(0)], [Float(0), Float(0), Float(0)]
            cov_d, cov_di, cov, cov_i = Float(0), Float(0), Float(0), Float(0)
            for pix, wgt, inside in bilinear_taps(u, v, wi, hi, use):
                pix = ioff + pix
                depth = dr.gather(Float, self.depths, pix, inside)
                wdep = dr.select(dr.abs(depth - dist) <= tol_p, wgt, 0.0)
                tap = [dr.gather(Float, self.images, pix * 4 + ch, inside) for ch in range(4)]
                t_all, t_in = dr.abs(tap[3]), dr.maximum(tap[3], 0.0)
                for ch in range(3):
                    col[ch] += wgt * t_all * tap[ch]
                    col_d[ch] += wdep * t_all * tap[ch]
                    col_i[ch] += wgt * t_in * tap[ch]
                    col_di[ch] += wdep * t_in * tap[ch]
                cov += wgt * t_all
                cov_d += wdep * t_all
                cov_i += wgt * t_in
                cov_di += wdep * t_in
            ok = use & (cov > 1e-3)
            seen = use & (cov_d > 1e-3)
            inner_d, inner = cov_di > 1e-3, cov_i > 1e-3
            seen_col = [dr.select(inner_d, col_di[ch] * dr.rcp(cov_di), col_d[ch] * dr.select(seen, dr.rcp(cov_d), 0.0))
                        for ch in range(3)]
            any_col = [dr.select(inner, col_i[ch] * dr.rcp(cov_i), col[ch] * dr.select(ok, dr.rcp(cov), 0.0))
                       for ch in range(3)]
            out = []
            # a chunk that has only outline texels for the point weighs OUTLINE_WEIGHT of its weight: the
            # chunks that see the point off their outline give its colour wherever there is one
            low = dr.opaque(Float, OUTLINE_WEIGHT)
            kd, ka = dr.select(inner_d, 1.0, low), dr.select(inner, 1.0, low)
            # accumulators: (primary, seen), (fallback, seen), (fallback, regardless of depth)
            for k, (wt, c3) in enumerate(((dr.select(seen, a * kd, 0.0), seen_col), (dr.select(seen, af * kd, 0.0), seen_col),
                                          (dr.select(ok, af * ka, 0.0), any_col))):
                out += [acc[4 * k + ch] + wt * c3[ch] for ch in range(3)] + [acc[4 * k + 3] + wt]
            return (j + 1, *out)

        zeros = [dr.opaque(Float, 0, n) for _ in range(12)]
        state = dr.while_loop((UInt32(first), *zeros), cond, body)
        acc = state[1:]
        primary, fallback, anyway = acc[3] > 1e-9, acc[7] > 1e-9, acc[11] > 1e-9
        pick = [dr.select(primary, acc[j], dr.select(fallback, acc[4 + j], acc[8 + j])) for j in range(4)]
        inv = dr.select(pick[3] > 1e-9, dr.rcp(pick[3]), 0.0)
        colour = mi.Color3f(pick[0] * inv, pick[1] * inv, pick[2] * inv)
        return colour, active & (pick[3] > 1e-9), active & ~primary & ~fallback & anyway
