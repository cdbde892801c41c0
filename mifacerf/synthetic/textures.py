"""Skin textures: xatlas UV atlas, texel → surface map, albedo / roughness / normal maps, wrinkles.

Texture-space conventions (checked against Mitsuba 3.9's ``bitmap`` texture and ``normalmap`` BSDF):

* an image of shape ``(H, W, C)`` covers ``uv ∈ [0, 1]²``; texel ``(row r, column c)`` is centred at
  ``uv = ((c + ½)/W, (r + ½)/H)`` (no flip: row 0 is v ≈ 0);
* the **normal map** stores a tangent-space normal ``n_t`` encoded as ``(n_t + 1)/2``; its frame is
  Mitsuba's shading frame: ``s = normalize(dp/du − n⟨n, dp/du⟩)``, ``t = n × s``, ``n`` = the
  interpolated shading normal (``src/bsdfs/normalmap.cpp`` evaluates the map in ``si.sh_frame``,
  which a mesh builds from ``dp_du`` exactly like this; ``tests/synthetic`` checks it by rendering).

**Wrinkles** are families of fine creases, each with a fixed place, a line pattern (the level sets of
a phase function on the neutral surface) and a compression direction (the phase gradient). Per
expression, each family's activation at a vertex is the skin's compressive strain along that
direction relative to the neutral face, from the deformed vs neutral triangle metric, averaged over
the vertex's triangles; texels interpolate it through the texel → (triangle, barycentric) map. Active
creases deepen the normal map (slopes up to ~0.4) and darken the albedo a little (cavities). At the
neutral face the strain, hence every activation, is exactly zero.
"""
from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np
import scipy.ndimage as ndi
import scipy.sparse as sp

from . import head as H
from .expressions import gauss, smoothstep

SKIN_BASE = np.array([0.62, 0.40, 0.30])
LIP_COLOUR = np.array([0.50, 0.15, 0.14])
HAIR_COLOUR = np.array([0.045, 0.030, 0.022])
DOT_COLOUR = np.array([0.90, 0.85, 0.10])


# --------------------------------------------------------------------------------------------
# atlas
# --------------------------------------------------------------------------------------------
def build_atlas(V: np.ndarray, F: np.ndarray, resolution: int, importance=None, low_scale: float = 0.45) -> dict:
    """xatlas UV atlas of a mesh: ``uv`` (V_uv, 2) in [0, 1], ``uv_faces`` (F, 3) indices into
    ``uv`` (same face order as ``F``), ``uv_vertex`` (V_uv,) the mesh vertex of each uv vertex
    (atlas seams duplicate vertices).

    ``importance`` (F,) bool: faces that get full texel density; the others (e.g. scalp, back of the
    neck) are handed to xatlas as a second mesh scaled by ``low_scale`` (uniformly, so without
    distortion) and so get ``low_scale`` × the density."""
    import xatlas

    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    groups = [np.arange(len(F))] if importance is None else \
        [np.nonzero(importance)[0], np.nonzero(~np.asarray(importance, bool))[0]]
    groups = [g for g in groups if len(g)]
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()
    atlas = xatlas.Atlas()
    maps = []
    for gi, g in enumerate(groups):
        used, inv = np.unique(F[g], return_inverse=True)
        scale = 1.0 if gi == 0 else low_scale
        atlas.add_mesh(np.ascontiguousarray(V[used] * scale, np.float32),
                       np.ascontiguousarray(inv.reshape(-1, 3), np.uint32))
        maps.append(used)
    co = xatlas.ChartOptions()
    co.max_chart_area = float(area / 30.0)   # bounded charts: several times faster than unbounded
    co.max_boundary_length = float(np.sqrt(area) * 0.58)
    po = xatlas.PackOptions()
    po.resolution = int(resolution)
    po.padding = 2
    po.bilinear = True
    po.blockAlign = True
    atlas.generate(co, po)
    if atlas.atlas_count != 1:
        raise RuntimeError(f"xatlas produced {atlas.atlas_count} atlases")
    uv_all, uvf_all, uvv_all = [], np.zeros((len(F), 3), np.int64), []
    off = 0
    for gi, g in enumerate(groups):
        vm, idx, uv = atlas[gi]
        uv_all.append(np.asarray(uv, np.float64))
        uvv_all.append(maps[gi][np.asarray(vm, np.int64)])
        uvf_all[g] = np.asarray(idx, np.int64) + off
        off += len(uv)
    return dict(uv=np.concatenate(uv_all), uv_faces=uvf_all.astype(np.int32),
                uv_vertex=np.concatenate(uvv_all).astype(np.int32))


def rasterize(uv: np.ndarray, uv_faces: np.ndarray, res: int, gutter: int = 6):
    """Texel → (triangle, barycentric) map of an atlas at ``res × res``.

    Returns ``tri`` (res², ) int32 (−1 where no triangle and beyond the gutter), ``bary``
    (res², 3) float32 and ``inside`` (res², ) bool. Texels within ``gutter`` texels of a chart take
    the nearest covered texel's triangle with barycentrics clamped onto it (so bilinear lookups
    across chart borders read sensible values)."""
    T = uv[uv_faces] * res - 0.5          # texel-centre coordinates (c, r)
    lo = np.floor(T.min(axis=1)).astype(int)
    hi = np.ceil(T.max(axis=1)).astype(int)
    lo = np.clip(lo, 0, res - 1)
    hi = np.clip(hi, 0, res - 1)
    w = hi[:, 0] - lo[:, 0] + 1
    h = hi[:, 1] - lo[:, 1] + 1
    n = w * h
    fid = np.repeat(np.arange(len(T)), n)
    start = np.concatenate([[0], np.cumsum(n)[:-1]])
    k = np.arange(n.sum()) - np.repeat(start, n)
    cc = lo[fid, 0] + k % w[fid]
    rr = lo[fid, 1] + k // w[fid]
    bary = _barycentric(T[fid], np.stack([cc, rr], 1).astype(float))
    ok = np.all(bary >= -1e-7, axis=1)
    fid, cc, rr, bary = fid[ok], cc[ok], rr[ok], bary[ok]
    tri = np.full(res * res, -1, np.int32)
    B = np.zeros((res * res, 3), np.float32)
    lin = rr * res + cc
    tri[lin] = fid
    B[lin] = bary
    inside = tri >= 0
    # gutter: nearest covered texel's triangle, barycentrics clamped
    dist, (ir, ic) = ndi.distance_transform_edt(~inside.reshape(res, res), return_indices=True)
    g = (~inside) & (dist.ravel() <= gutter)
    gi = np.nonzero(g)[0]
    src = (ir.ravel() * res + ic.ravel())[gi]
    tri[gi] = tri[src]
    rr_g, cc_g = np.divmod(gi, res)
    b = _barycentric(T[tri[gi]], np.stack([cc_g, rr_g], 1).astype(float))
    b = np.clip(b, 0.0, None)
    b /= b.sum(axis=1, keepdims=True)
    B[gi] = b
    return tri, B, inside


def _barycentric(tri2d, p):
    a, b, c = tri2d[:, 0], tri2d[:, 1], tri2d[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    d = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    d = np.where(np.abs(d) < 1e-30, 1e-30, d)
    l1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / d
    l2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / d
    return np.stack([1.0 - l1 - l2, l1, l2], 1)


# --------------------------------------------------------------------------------------------
# procedural noise on 3-D positions (seamless across charts)
# --------------------------------------------------------------------------------------------
_TABLE = np.random.default_rng(20040101).random(64 ** 3)


def value_noise(P, scale, seed=0, grad=False):
    """Smooth value noise in [0, 1] at points ``P`` (n, 3) with feature size ``scale`` (m); with
    ``grad`` also its gradient (n, 3) (per metre). Lattice values come from a fixed random table
    (period 64 cells, offset per seed)."""
    q = P / scale + (np.array([17.0, 31.0, 47.0]) * (seed % 9973))
    i0 = np.floor(q)
    f = q - i0
    i0 = i0.astype(np.int64)
    u = f * f * f * (f * (f * 6 - 15) + 10)
    du = 30.0 * f * f * (f - 1.0) ** 2
    ix = [(i0[:, 0] & 63) * 4096, ((i0[:, 0] + 1) & 63) * 4096]
    iy = [(i0[:, 1] & 63) * 64, ((i0[:, 1] + 1) & 63) * 64]
    iz = [i0[:, 2] & 63, (i0[:, 2] + 1) & 63]
    c = {}
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                c[dx, dy, dz] = _TABLE[ix[dx] + iy[dy] + iz[dz]]
    ux, uy, uz = u[:, 0], u[:, 1], u[:, 2]
    # trilinear blend
    x00 = c[0, 0, 0] + ux * (c[1, 0, 0] - c[0, 0, 0])
    x10 = c[0, 1, 0] + ux * (c[1, 1, 0] - c[0, 1, 0])
    x01 = c[0, 0, 1] + ux * (c[1, 0, 1] - c[0, 0, 1])
    x11 = c[0, 1, 1] + ux * (c[1, 1, 1] - c[0, 1, 1])
    y0 = x00 + uy * (x10 - x00)
    y1 = x01 + uy * (x11 - x01)
    val = y0 + uz * (y1 - y0)
    if not grad:
        return val
    dx00 = c[1, 0, 0] - c[0, 0, 0]
    dx10 = c[1, 1, 0] - c[0, 1, 0]
    dx01 = c[1, 0, 1] - c[0, 0, 1]
    dx11 = c[1, 1, 1] - c[0, 1, 1]
    gy0 = dx00 + uy * (dx10 - dx00)
    gy1 = dx01 + uy * (dx11 - dx01)
    gx = (gy0 + uz * (gy1 - gy0)) * du[:, 0]
    gyv = ((x10 - x00) + uz * ((x11 - x01) - (x10 - x00))) * du[:, 1]
    gz = (y1 - y0) * du[:, 2]
    return val, np.stack([gx, gyv, gz], 1) / scale


def fbm(P, scale, octaves=4, seed=0, gain=0.5):
    tot, amp, norm = 0.0, 1.0, 0.0
    for o in range(octaves):
        tot = tot + amp * value_noise(P, scale / 2 ** o, seed + 101 * o)
        norm += amp
        amp *= gain
    return tot / norm


# --------------------------------------------------------------------------------------------
# regions (on neutral head-frame positions)
# --------------------------------------------------------------------------------------------
def head_azimuth(P):
    return np.arctan2(P[:, 0], P[:, 2] - H.AXIS_Z)


def vermilion_mask(P, hw=H.MOUTH_HALF_WIDTH):
    """Red of the lips (soft edged, ~0.3 mm)."""
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    eta = y - H.Y_MOUTH
    r = np.clip(1.0 - (x / hw) ** 2, 0.0, None)
    hu = 0.0068 * r ** 0.45 + 0.0006 * gauss((np.abs(x) - 0.0052) / 0.0024) - 0.0007 * gauss(x / 0.0020)
    hl = 0.0090 * np.clip(1.0 - (x / (0.98 * hw)) ** 2, 0.0, None) ** 0.55
    up = smoothstep(hu + 0.0003, hu - 0.0003, eta) * (eta >= -1e-9)
    lo = smoothstep(hl + 0.0003, hl - 0.0003, -eta) * (eta <= 1e-9)
    m = np.maximum(up, lo) * (r > 0) * smoothstep(0.055, 0.065, z)
    return np.clip(m, 0.0, 1.0)


def hair_mask(P, seed=3):
    """Short scalp hair above an irregular hairline (with sideburns)."""
    hl = H.hairline_y(P)
    jitter = (fbm(P, 0.006, 3, seed) - 0.5) * 0.006
    return smoothstep(-0.002, 0.003, P[:, 1] - hl + jitter)


def brow_mask(P, seed=5):
    """Eyebrows: an arch over each eye, thick medially, with hair strokes."""
    x, y = P[:, 0], P[:, 1]
    ax = np.abs(x)
    yc = np.interp(ax, [0.010, 0.014, 0.038, 0.058], [0.0150, 0.0168, 0.0255, 0.0185])
    th = np.interp(ax, [0.010, 0.014, 0.040, 0.058], [0.0, 0.0060, 0.0042, 0.0010])
    m = smoothstep(0.5 * th + 0.0012, 0.5 * th - 0.0008, np.abs(y - yc)) * (P[:, 2] > 0.04)
    strokes = value_noise(P * np.array([1.0, 0.25, 1.0]) + np.array([0.0, 0.0, 0.0]), 0.0008, seed)
    return np.clip(m * (0.55 + 0.6 * strokes), 0.0, 1.0)


def stubble_mask(P):
    x, y, z = P[:, 0], P[:, 1], P[:, 2]
    chin = smoothstep(-0.048, -0.062, y) * smoothstep(-0.125, -0.100, y)
    lip = smoothstep(-0.060, -0.056, y) * smoothstep(-0.042, -0.048, y) * (np.abs(x) < 0.03)
    cheek = smoothstep(-0.030, -0.060, y) * smoothstep(0.02, 0.05, np.abs(x))
    front = smoothstep(0.0, 0.03, z)
    return np.clip(np.maximum(np.maximum(chin, lip), cheek) * front, 0.0, 1.0)


# --------------------------------------------------------------------------------------------
# wrinkle families
# --------------------------------------------------------------------------------------------
@dataclass
class Family:
    name: str
    mask: callable        # P -> [0, 1]
    phase: callable       # P -> phase (crease lines at integer values)
    depth: float          # crease depth at full activation (m)
    width: float = 0.18   # crease half-width (fraction of the spacing)
    gain: float = 7.0     # activation = gain * (compression - dead zone), clipped
    dead: float = 0.03
    single: bool = False  # one fold at phase 0 only


def _families():
    eL = H.EYE_CENTRE
    fam = []

    def front(P):
        return smoothstep(0.02, 0.05, P[:, 2])

    fam.append(Family(
        "forehead",
        lambda P: gauss(P[:, 0] / 0.036) * smoothstep(0.028, 0.040, P[:, 1]) * smoothstep(0.082, 0.068, P[:, 1]) * front(P),
        lambda P: (P[:, 1] + 0.0012 * np.sin(P[:, 0] / 0.011) + 0.0007 * np.sin(P[:, 0] / 0.0047 + 1.3)) / 0.0040,
        0.00050, gain=9.0))
    fam.append(Family(
        "glabella",
        lambda P: gauss(P[:, 0] / 0.009) * gauss((P[:, 1] - 0.022) / 0.009) * front(P),
        lambda P: P[:, 0] / 0.0042 + 0.5 + 0.08 * np.sin(P[:, 1] / 0.004),
        0.00045))
    for sgn, sfx in ((1.0, "L"), (-1.0, "R")):
        c = np.array([sgn * 0.0465, H.Y_EYE, 0.0])

        def crow_mask(P, c=c, sgn=sgn):
            d = np.hypot(P[:, 0] - c[0], P[:, 1] - c[1])
            lat = smoothstep(-0.001, 0.004, sgn * (P[:, 0] - c[0]))
            return smoothstep(0.004, 0.008, d) * smoothstep(0.024, 0.016, d) * lat * smoothstep(0.0, 0.03, P[:, 2])

        def crow_phase(P, c=c, sgn=sgn):
            return np.arctan2(P[:, 1] - c[1], sgn * (P[:, 0] - c[0])) / 0.17

        fam.append(Family(f"crows_feet_{sfx}", crow_mask, crow_phase, 0.00055, width=0.22, gain=8.0))

        a = np.array([sgn * 0.0205, -0.036])
        b = np.array([sgn * 0.0335, -0.078])

        def nl_mask(P, a=a, b=b):
            ab = b - a
            t = np.clip(((P[:, 0] - a[0]) * ab[0] + (P[:, 1] - a[1]) * ab[1]) / (ab @ ab), 0.0, 1.0)
            return (smoothstep(0.0, 0.12, t) * smoothstep(1.0, 0.8, t) * smoothstep(0.04, 0.06, P[:, 2])
                    * smoothstep(0.006, 0.003, np.abs(_seg_dist(P, a, b))))

        def nl_phase(P, a=a, b=b, sgn=sgn):
            return _seg_dist(P, a, b) * sgn / 0.0040

        fam.append(Family(f"nasolabial_{sfx}", nl_mask, nl_phase, 0.0016, width=0.38, gain=7.0,
                          dead=0.05, single=True))
        ce = eL * np.array([sgn, 1, 1])

        def ue_mask(P, ce=ce):
            d = np.hypot(P[:, 0] - ce[0], P[:, 1] - ce[1])
            return (smoothstep(0.013, 0.016, d) * smoothstep(0.026, 0.020, d) * (P[:, 1] < H.Y_EYE - 0.002)
                    * smoothstep(0.05, 0.06, P[:, 2]))

        def ue_phase(P, ce=ce):
            return np.hypot(P[:, 0] - ce[0], (P[:, 1] - ce[1]) * 1.2) / 0.0026

        fam.append(Family(f"under_eye_{sfx}", ue_mask, ue_phase, 0.00025))
    fam.append(Family(
        "nose_bridge",
        lambda P: gauss(P[:, 0] / 0.009) * gauss((P[:, 1] + 0.002) / 0.008) * smoothstep(0.07, 0.08, P[:, 2]),
        lambda P: (P[:, 1] + 0.0006 * np.sin(P[:, 0] / 0.004)) / 0.0030,
        0.00030))
    fam.append(Family(
        "lip_lines",
        lambda P: gauss(P[:, 0] / 0.020) * gauss((P[:, 1] - H.Y_MOUTH) / 0.011) * smoothstep(0.06, 0.075, P[:, 2]),
        lambda P: P[:, 0] / 0.0022 + 0.3 * np.sin(P[:, 1] / 0.003),
        0.00022, gain=5.0, dead=0.08))
    fam.append(Family(
        "neck",
        lambda P: smoothstep(-0.200, -0.180, P[:, 1]) * smoothstep(-0.118, -0.132, P[:, 1]) * smoothstep(-0.01, 0.02, P[:, 2]),
        lambda P: (P[:, 1] + 0.002 * np.sin(P[:, 0] / 0.02)) / 0.0060,
        0.00045))
    return fam


def _seg_dist(P, a, b):
    """Signed distance in the x-y plane from the segment a-b (positive on the lateral side)."""
    ab = b - a
    t = np.clip(((P[:, 0] - a[0]) * ab[0] + (P[:, 1] - a[1]) * ab[1]) / (ab @ ab), 0.0, 1.0)
    cx = a[0] + t * ab[0]
    cy = a[1] + t * ab[1]
    d = np.hypot(P[:, 0] - cx, P[:, 1] - cy)
    side = np.sign((P[:, 0] - a[0]) * ab[1] - (P[:, 1] - a[1]) * ab[0])
    return d * side * np.sign(ab[1]) * -1.0


def _crease(phase, width, single):
    """Crease profile c ∈ [0, 1] (1 at the crease bottom) and dc/dphase."""
    d = phase if single else phase - np.round(phase)
    c = np.exp(-(d / width) ** 2)
    return c, c * (-2.0 * d / width ** 2)


def _grad(fn, P, eps=2e-5):
    g = np.empty_like(P)
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        g[:, k] = (fn(P + e) - fn(P - e)) / (2 * eps)
    return g


# --------------------------------------------------------------------------------------------
# the skin texture set
# --------------------------------------------------------------------------------------------
def vertex_normals(V, F):
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    N = np.zeros_like(V)
    for k in range(3):
        np.add.at(N, F[:, k], n)
    return N / np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-30)


class SkinTextures:
    """Static maps plus the per-expression wrinkle machinery for one skin atlas.

    ``neutral``: (V, 3) neutral skin vertices (head frame); ``faces`` (F, 3); ``atlas``: dict of
    :func:`build_atlas`; ``dots``: (D, 3) neutral dot centres and ``dot_radius`` (m)."""

    def __init__(self, neutral, faces, atlas, res, dots, dot_radius, static=None, raster=None):
        self.res = res
        self.faces = faces
        self.neutral = neutral
        if raster is None:
            raster = rasterize(atlas["uv"], atlas["uv_faces"], res)
        tri, bary, inside = raster
        self.raster = (tri, bary, inside)
        self.covered = np.nonzero(tri >= 0)[0]
        self.inside = inside
        self.tex_tri = tri[self.covered]
        self.tex_bary = bary[self.covered].astype(np.float64)
        fv = faces[self.tex_tri]                                   # (T, 3) vertex ids
        self.tex_fv = fv
        P = np.einsum("tk,tkj->tj", self.tex_bary, neutral[fv])
        self.tex_pos = P
        # shading frame at each texel (neutral): s along dp/du, t = n x s
        N = vertex_normals(neutral, faces)
        n = np.einsum("tk,tkj->tj", self.tex_bary, N[fv])
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        dpdu = _dp_du(neutral, faces, atlas)[self.tex_tri]
        s = dpdu - n * np.einsum("ij,ij->i", n, dpdu)[:, None]
        s /= np.maximum(np.linalg.norm(s, axis=1, keepdims=True), 1e-30)
        t = np.cross(n, s)
        self.frame = (s, t, n)
        if static is None:      # rounded as the cache stores them, so a cold and a warm cache agree bit for bit
            static = {k: v.astype(np.float16) for k, v in self._static_maps(dots, dot_radius).items()}
        self.albedo = static["albedo"].astype(np.float32)
        self.roughness = static["roughness"].astype(np.float32)
        self.base_slopes = static["slopes"].astype(np.float32)   # (res*res, 2)
        self.normal_map = encode_normals(self.base_slopes).reshape(res, res, 3)
        for a in (self.albedo, self.roughness, self.normal_map):
            a.flags.writeable = False      # shared by every pose without wrinkles
        self._setup_wrinkles()

    # ------------------------------------------------------------------------------------------
    def _static_maps(self, dots, dot_radius):
        res = self.res
        P = self.tex_pos
        n_all = res * res
        n1 = fbm(P, 0.030, 3, 11)
        n2 = fbm(P, 0.004, 3, 12)
        pores = value_noise(P, 0.0007, 13)
        col = SKIN_BASE[None] * (0.93 + 0.14 * n1[:, None]) * (0.97 + 0.06 * n2[:, None])
        col *= (0.98 + 0.04 * pores[:, None])
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        # redness: cheeks, nose, ears; eyelids slightly darker and pinker
        red = (0.7 * gauss(np.hypot(np.abs(x) - 0.040, y + 0.020) / 0.014)
               + 0.6 * gauss(np.hypot(x, y + 0.030) / 0.010) * (z > 0.09)
               + 0.5 * smoothstep(0.060, 0.075, np.abs(x)) * gauss((y + 0.012) / 0.03) * (z < 0.02))
        col += red[:, None] * np.array([0.05, -0.03, -0.02])
        for sgn in (1.0, -1.0):
            ce = H.EYE_CENTRE * np.array([sgn, 1, 1])
            d = np.linalg.norm(P - ce, axis=1)
            lid = smoothstep(0.024, 0.015, d)
            col *= (1.0 - lid[:, None] * np.array([0.03, 0.07, 0.05]))
        # freckles: sparse small spots over the nose and cheeks
        fr = value_noise(P, 0.0016, 21)
        fz = gauss(np.hypot(x / 0.05, (y + 0.01) / 0.035)) * (z > 0.05)
        spots = smoothstep(0.90, 0.95, fr) * fz
        col = col * (1 - 0.20 * spots[:, None]) + spots[:, None] * np.array([0.10, 0.04, 0.01]) * 0.20
        # stubble shadow
        st = stubble_mask(P) * (0.6 + 0.4 * value_noise(P, 0.0005, 31))
        col *= (1.0 - 0.10 * st[:, None])
        # nostrils dark
        for sgn in (1.0, -1.0):
            c = np.array([sgn * 0.0066, -0.0428, 0.0985])
            nd = np.linalg.norm((P - c) / np.array([0.0040, 0.0028, 0.0058]), axis=1)
            col *= (1.0 - 0.85 * smoothstep(1.3, 0.7, nd))[:, None]
        # lips
        vm = vermilion_mask(P)
        lipc = LIP_COLOUR * (0.92 + 0.16 * n2[:, None]) * (0.96 + 0.08 * value_noise(P * [1, 3, 1], 0.0015, 41)[:, None])
        col = col * (1 - vm[:, None]) + lipc * vm[:, None]
        # brows and scalp hair
        bm = brow_mask(P)
        col = col * (1 - 0.9 * bm[:, None]) + 0.9 * bm[:, None] * HAIR_COLOUR * 1.4
        hm = hair_mask(P)
        strands = value_noise(P * np.array([1.0, 0.35, 1.0]), 0.0007, 51)
        hc = HAIR_COLOUR * (0.7 + 0.6 * strands[:, None])
        col = col * (1 - hm[:, None]) + hc * hm[:, None]
        # roughness
        tz = gauss(np.hypot(x / 0.030, (y - 0.05) / 0.03)) + gauss(np.hypot(x / 0.010, (y + 0.01) / 0.03))
        rough = 0.46 - 0.10 * np.clip(tz, 0, 1) + 0.04 * (n1 - 0.5)
        rough = rough * (1 - vm) + 0.30 * vm
        rough = rough * (1 - bm) + 0.60 * bm
        rough = rough * (1 - hm) + 0.70 * hm
        # dots (painted last: ink over everything)
        if len(dots):
            from scipy.spatial import cKDTree

            d, _ = cKDTree(dots).query(P, k=1, distance_upper_bound=4 * dot_radius)
            cov = smoothstep(dot_radius + 0.00012, dot_radius - 0.00012, d)
            col = col * (1 - cov[:, None]) + DOT_COLOUR[None] * cov[:, None]
            rough = rough * (1 - cov) + 0.40 * cov
        # fine bumps (pores / orange-peel): slopes in the tangent frame
        s, t, n = self.frame
        g = 0.000012 * value_noise(P, 0.0010, 61, grad=True)[1] + 0.000004 * value_noise(P, 0.0005, 62, grad=True)[1]
        slopes = np.stack([np.einsum("ij,ij->i", g, s), np.einsum("ij,ij->i", g, t)], 1)
        slopes *= (1.0 - 0.7 * hm)[:, None]
        albedo = np.zeros((n_all, 3), np.float32)
        roughness = np.full(n_all, 0.5, np.float32)
        sl = np.zeros((n_all, 2), np.float32)
        albedo[self.covered] = np.clip(col, 0.0, 1.0)
        roughness[self.covered] = np.clip(rough, 0.05, 1.0)
        sl[self.covered] = slopes
        return dict(albedo=albedo.reshape(res, res, 3), roughness=roughness.reshape(res, res),
                    slopes=sl)

    def static_arrays(self):
        return dict(albedo=self.albedo.astype(np.float16), roughness=self.roughness.astype(np.float16),
                    slopes=self.base_slopes.astype(np.float16))

    # ------------------------------------------------------------------------------------------
    def _setup_wrinkles(self):
        P = self.tex_pos
        s, t, n = self.frame
        F = self.faces
        V0 = self.neutral
        nV = len(V0)
        self.families = _families()
        self.fam = []
        e1 = V0[F[:, 1]] - V0[F[:, 0]]
        e2 = V0[F[:, 2]] - V0[F[:, 0]]
        self._e0 = (e1, e2)
        cent = V0[F].mean(axis=1)
        for f in self.families:
            m = f.mask(P)
            sel = np.nonzero(m > 1e-3)[0]
            Ps = P[sel]
            ph = f.phase(Ps)
            c, dc = _crease(ph, f.width, f.single)
            noise = 0.45 + 0.55 * value_noise(Ps, 0.006, zlib.crc32(f.name.encode()) % 1000)
            amp = m[sel] * noise * f.depth
            hgt = -amp * c
            gph = _grad(f.phase, Ps)
            G = (-amp * dc)[:, None] * gph
            Gs = np.einsum("ij,ij->i", G, s[sel])
            Gt = np.einsum("ij,ij->i", G, t[sel])
            # per-face compression direction (phase gradient at the centroid, in the face plane)
            fm = f.mask(cent)
            fsel = np.nonzero(fm > 1e-3)[0]
            d = _grad(f.phase, cent[fsel])
            fn = np.cross(e1[fsel], e2[fsel])
            fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-30)
            d = d - fn * np.einsum("ij,ij->i", fn, d)[:, None]
            d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
            # coefficients c with [e1 e2] c = d
            A = np.stack([e1[fsel], e2[fsel]], 2)            # (f, 3, 2)
            AtA = np.einsum("fki,fkj->fij", A, A)
            Atd = np.einsum("fki,fk->fi", A, d)
            coef = np.linalg.solve(AtA, Atd[..., None])[..., 0]
            # vertex <- face averaging (area weighted)
            area = 0.5 * np.linalg.norm(np.cross(e1[fsel], e2[fsel]), axis=1) * fm[fsel]
            rows = F[fsel].ravel()
            cols = np.repeat(np.arange(len(fsel)), 3)
            vals = np.repeat(area, 3)
            M = sp.csr_matrix((vals, (rows, cols)), shape=(nV, len(fsel)))
            norm = np.asarray(M.sum(axis=1)).ravel()
            M = sp.diags(1.0 / np.maximum(norm, 1e-30)) @ M
            self.fam.append(dict(f=f, texels=self.covered[sel], tex_fv=self.tex_fv[sel],
                                 tex_bary=self.tex_bary[sel], h=hgt, crease=c * m[sel] * noise,
                                 Gs=Gs, Gt=Gt, faces=fsel, coef=coef, M=M))
        self.wrinkle_texels = np.unique(np.concatenate([d["texels"] for d in self.fam]))

    def activations(self, V):
        """Per family: per-vertex activation (V,) for deformed skin ``V`` (head frame or world:
        only the metric matters)."""
        F = self.faces
        out = {}
        for d in self.fam:
            fs = d["faces"]
            f = F[fs]
            e1 = V[f[:, 1]] - V[f[:, 0]]
            e2 = V[f[:, 2]] - V[f[:, 0]]
            v = d["coef"][:, :1] * e1 + d["coef"][:, 1:] * e2
            lam = np.linalg.norm(v, axis=1)
            comp = np.clip(1.0 - lam, 0.0, None)
            cv = d["M"] @ comp
            fam = d["f"]
            out[fam.name] = np.clip((cv - fam.dead) * fam.gain, 0.0, 1.5)
        return out

    def for_pose(self, V):
        """Albedo (res, res, 3), normal map (res, res, 3) and the activations for skin ``V``."""
        acts = self.activations(V)
        res = self.res
        if not any(np.any(a > 0) for a in acts.values()):
            return self.albedo, self.normal_map, acts
        albedo = self.albedo.reshape(-1, 3).copy()
        slopes = self.base_slopes.copy()
        dark = np.zeros(res * res, np.float32)
        for d in self.fam:
            a = acts[d["f"].name]
            at = np.einsum("tk,tk->t", d["tex_bary"], a[d["tex_fv"]])
            if not np.any(at > 0):
                continue
            tx = d["texels"]
            slopes[tx, 0] += (at * d["Gs"]).astype(np.float32)
            slopes[tx, 1] += (at * d["Gt"]).astype(np.float32)
            dark[tx] += (at * d["crease"]).astype(np.float32)
        wt = self.wrinkle_texels
        albedo[wt] *= (1.0 - 0.35 * np.clip(dark[wt], 0.0, 1.0))[:, None]
        nm = self.normal_map.reshape(-1, 3).copy()
        nm[wt] = encode_normals(slopes[wt])
        return albedo.reshape(res, res, 3), nm.reshape(res, res, 3), acts


def encode_normals(slopes):
    """Tangent-space normal from height slopes (dh/ds, dh/dt), encoded to [0, 1]."""
    n = np.concatenate([-slopes, np.ones((len(slopes), 1), slopes.dtype)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return ((n + 1.0) * 0.5).astype(np.float32)


def _dp_du(V, F, atlas):
    """Per-face dp/du of the atlas parameterisation (3-vectors)."""
    uv = atlas["uv"][atlas["uv_faces"]]
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    d1 = uv[:, 1] - uv[:, 0]
    d2 = uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    det = np.where(np.abs(det) < 1e-20, 1e-20, det)
    return (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
