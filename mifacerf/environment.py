"""Lighting environments: lat-long maps, generated environments, and their reduction
to the light stage's basis.

Lat-long convention (docs/conventions.md), identical to Mitsuba's ``envmap`` with an
identity ``to_world``: for a **world** direction ``d`` towards the environment,
``u = atan2(d.x, −d.z) / 2π (mod 1)``, ``v = acos(d.y) / π``. Top row = +Y (up),
map centre = +Z (in front of the face), u = ¼ is +X. Arrays are ``(H, W, 3)`` linear
sRGB radiance with ``W = 2H``.

The light-stage basis: a lighting environment becomes one RGB weight per light,
``L_l = ∫_{cell l} E(ω) dω`` over the light's spherical-Voronoi cell (the set of
directions nearer to light ``l`` than to any other). Relighting is then
``Σ_l L_l · OLAT_l`` because each OLAT image is the response to unit irradiance.
That rule (``voronoi``) is the default of :data:`LIGHT_BASIS_METHODS`; ``hat`` shares each
direction among its spherical Delaunay triangle's three lights instead (:func:`hat_shares`).
:func:`light_basis` computes it by supersampling the sphere and evaluating the
environment through Mitsuba's own emitter (so it matches what Mitsuba's path
tracer sees exactly); the sum over lights equals the environment's total
∫E dω (energy conserving) up to the quadrature.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .imageio import read_hdr_or_exr, write_exr
from .jitarrays import from_jit, to_jit
from .errors import MifacerfError


class EnvironmentError_(MifacerfError, ValueError):
    """An environment map of the wrong shape or with invalid values."""


# ----------------------------------------------------------------- convention
def direction_to_uv(d: np.ndarray) -> np.ndarray:
    """(..., 3) world directions → (..., 2) lat-long (u, v) in [0, 1)."""
    d = np.asarray(d, np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    u = np.mod(np.arctan2(d[..., 0], -d[..., 2]) / (2 * np.pi), 1.0)
    v = np.arccos(np.clip(d[..., 1], -1.0, 1.0)) / np.pi
    return np.stack([u, v], axis=-1)


def uv_to_direction(uv: np.ndarray) -> np.ndarray:
    """(..., 2) lat-long (u, v) → (..., 3) unit world directions (inverse of :func:`direction_to_uv`)."""
    uv = np.asarray(uv, np.float64)
    phi = uv[..., 0] * 2 * np.pi
    theta = uv[..., 1] * np.pi
    s = np.sin(theta)
    # atan2(x, -z) = phi  →  x = sin(phi), -z = cos(phi)
    return np.stack([s * np.sin(phi), np.cos(theta), -s * np.cos(phi)], axis=-1)


def latlong_grid(height: int, width: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Texel-centre directions (H, W, 3) and exact texel solid angles (H, W) of a lat-long map."""
    width = 2 * height if width is None else width
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    uu, vv = np.meshgrid(u, v)
    dirs = uv_to_direction(np.stack([uu, vv], axis=-1))
    t0 = np.arange(height) / height * np.pi
    t1 = (np.arange(height) + 1) / height * np.pi
    row = (np.cos(t0) - np.cos(t1)) * (2 * np.pi / width)
    return dirs, np.repeat(row[:, None], width, axis=1)


def check_latlong(data: np.ndarray, name: str = "environment map") -> np.ndarray:
    """Validate a lat-long map: (H, 2H, 3), finite, non-negative. Returns float32."""
    data = np.asarray(data)
    if data.ndim != 3 or data.shape[2] < 3:
        raise EnvironmentError_(f"{name}: expected an (H, W, 3) image, got shape {data.shape}")
    h, w = data.shape[:2]
    if w != 2 * h:
        raise EnvironmentError_(f"{name}: a lat-long map must be twice as wide as high; got {w}x{h}")
    data = data[..., :3].astype(np.float32)
    if not np.isfinite(data).all():
        raise EnvironmentError_(f"{name}: contains NaN/Inf radiance")
    if (data < 0).any():
        raise EnvironmentError_(f"{name}: contains negative radiance")
    return data


@dataclass
class Environment:
    """A lat-long environment ``data`` (H, 2H, 3), linear sRGB radiance, world frame, plus a name."""

    data: np.ndarray
    name: str = "environment"

    def __post_init__(self):
        self.data = check_latlong(self.data, self.name)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "Environment":
        """Read a lat-long .exr or .hdr; errors name the file."""
        path = Path(path)
        try:
            return cls(read_hdr_or_exr(path), path.stem)
        except EnvironmentError_ as exc:
            raise EnvironmentError_(f"{path}: {exc}") from exc

    def save(self, path: str | os.PathLike) -> None:
        write_exr(path, self.data, half=False)

    def total_power(self) -> np.ndarray:
        """∫ E(ω) dω over the sphere with texels as constant patches, (3,)."""
        _, sa = latlong_grid(*self.data.shape[:2])
        return (self.data * sa[..., None]).sum(axis=(0, 1))

    def rotated(self, R: np.ndarray) -> "Environment":
        """The environment after rotating the world by ``R`` (3, 3): E'(ω) = E(Rᵀ ω). Bilinear resampling."""
        h, w = self.data.shape[:2]
        dirs, _ = latlong_grid(h, w)
        src = dirs @ np.asarray(R, np.float64)  # Rᵀ ω for each row vector
        return Environment(self.lookup(src), f"{self.name}-rotated")

    def lookup(self, d: np.ndarray) -> np.ndarray:
        """Radiance (..., 3) in world directions ``d`` (..., 3), bilinear like Mitsuba's envmap."""
        h, w = self.data.shape[:2]
        uv = direction_to_uv(d)
        x = uv[..., 0] * w - 0.5
        y = uv[..., 1] * h - 0.5
        x0 = np.floor(x).astype(np.int64)
        y0 = np.floor(y).astype(np.int64)
        fx, fy = x - x0, y - y0
        def tex(yy, xx):
            return self.data[np.clip(yy, 0, h - 1), np.mod(xx, w)]
        return ((1 - fy)[..., None] * ((1 - fx)[..., None] * tex(y0, x0) + fx[..., None] * tex(y0, x0 + 1))
                + fy[..., None] * ((1 - fx)[..., None] * tex(y0 + 1, x0) + fx[..., None] * tex(y0 + 1, x0 + 1)))

    def mitsuba_dict(self, scale: float = 1.0) -> dict:
        """A scene-dict entry for Mitsuba's ``envmap`` emitter showing this environment (identity to_world)."""
        mi = _mi()
        return {"type": "envmap", "bitmap": mi.Bitmap(self.data.astype(np.float32)), "scale": scale}


def _mi():
    from .variant import ensure_variant

    return ensure_variant()


# --------------------------------------------------------- light-stage basis
def sphere_quadrature(n_theta: int) -> tuple[np.ndarray, np.ndarray]:
    """Directions (N, 3) and exact solid angles (N,) of a lat-long cell grid with ``n_theta`` rows."""
    dirs, sa = latlong_grid(n_theta, 2 * n_theta)
    return dirs.reshape(-1, 3), sa.reshape(-1)


def evaluate_emitter(emitter, directions: np.ndarray, chunk: int = 1 << 20) -> np.ndarray:
    """Radiance (N, 3) of a Mitsuba emitter seen along world ``directions`` (N, 3) (infinite emitters)."""
    import drjit as dr

    mi = _mi()
    out = np.empty((len(directions), 3), np.float32)
    for s in range(0, len(directions), chunk):
        d = np.ascontiguousarray(directions[s:s + chunk], np.float32)
        si = dr.zeros(mi.SurfaceInteraction3f, len(d))
        si.wi = -to_jit(mi.Vector3f, d.T)
        val = emitter.eval(si)
        out[s:s + chunk] = from_jit(val)
    return out


def sample_emitter(emitter, height: int = 128, sub: int = 4) -> np.ndarray:
    """(height, 2 height, 3) float32 lat-long map of a Mitsuba infinite emitter, laid out as Mitsuba's
    ``envmap`` reads a bitmap — column i at u = (i + ½) / W, but row j at v = j / (H − 1), the first and last
    rows on the poles (not at (j + ½) / H, :func:`latlong_grid`'s texel centres) —, so that
    :meth:`Environment.mitsuba_dict` of the result shows the emitter again: an ``envmap`` of ``height`` rows
    is reproduced exactly by ``sub`` = 1.

    Each texel holds the emitter's mean radiance over the texel's part of the sphere (``sub`` x ``sub``
    stratified directions, weighted by sin θ; the pole rows span half a row), so light concentrated in
    features smaller than a texel (the windows of a captured probe) is kept where it is. Until 2026-12-04
    the facerf integrator sampled the scene's emitter at :func:`latlong_grid`'s centres and handed the
    rows to Mitsuba's layout: up to half a row towards the poles, 2 % of the light lost under ``uffizi.hdr``
    (docs/rendering.md, "The scene's environment as the exact path reads it"). Negative radiance is clamped
    to 0."""
    if height < 2 or sub < 1:
        raise ValueError(f"sample_emitter: height must be >= 2 and sub >= 1 (got {height}, {sub})")
    H, W = int(height), 2 * int(height)
    acc = np.zeros((H, W, 3))
    wsum = np.zeros((H, 1, 1))
    if sub == 1:   # the texel positions themselves (the pole rows on the poles)
        rows = [(np.arange(H) / (H - 1), np.ones((H, 1, 1)))]
    else:          # stratified in row j's span of v (clipped at the poles), weighted by sin θ × the span's length
        lo = np.maximum((np.arange(H) - 0.5) / (H - 1), 0.0)
        hi = np.minimum((np.arange(H) + 0.5) / (H - 1), 1.0)
        rows = [(v, (np.sin(v * np.pi) * (hi - lo))[:, None, None])
                for v in (lo + (hi - lo) * (dy + 0.5) / sub for dy in range(sub))]
    for v, wrow in rows:
        for dx in range(sub):
            u = (np.arange(W) + (dx + 0.5) / sub) / W
            uu, vv = np.meshgrid(u, v)
            d = uv_to_direction(np.stack([uu, vv], axis=-1)).reshape(-1, 3)
            acc += wrow * np.maximum(evaluate_emitter(emitter, d).reshape(H, W, 3), 0.0)
            wsum += wrow
    return (acc / np.maximum(wsum, 1e-300)).astype(np.float32)


def voronoi_shares(samples: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Light basis rule ``voronoi`` (the default): each sample direction belongs wholly to its nearest
    light, i.e. to that light's spherical-Voronoi cell. Returns lights (N, 1) and shares (N, 1) = 1."""
    from scipy.spatial import cKDTree

    _, cell = cKDTree(np.asarray(directions, np.float64)).query(samples)
    return cell[:, None], np.ones((len(cell), 1))


def hat_shares(samples: np.ndarray, directions: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
    """Light basis rule ``hat``: each sample direction is shared among the three lights of the spherical
    Delaunay triangle that holds it, by its barycentric coordinates in that triangle.

    The triangles are the facets of the lights' convex hull (the Delaunay triangulation of points on
    a sphere); a direction ω meets the facet (a, b, c) at the point ``ω t`` and its shares are that
    point's barycentric coordinates ``x / Σx`` with ``[a b c] x = ω`` (gnomonic, linear on the flat
    facet); the facet holding ω is the one whose ``x`` are all ≥ 0 (the facets' cones tile the sphere):
    on the hull plane the ray ω leaves through (largest ``n·ω / −offset``), the triangle of that plane
    with the largest ``min(x)`` (Qhull splits a plane holding more than three lights into several).
    Light l's weight is then ``∫ E(ω) h_l(ω) dω`` with the piecewise-linear "hat" h_l (1 at light l,
    0 at its Delaunay neighbours, Σ_l h_l = 1: energy is conserved as for ``voronoi``).
    Where four or more lights lie on one circle (the arm's rings) the triangulation is not unique and
    Qhull picks a diagonal. A layout without a hull about the centre (fewer than 4 lights, all on one
    great circle, all in one hemisphere) leaves directions no facet holds: those go to their nearest
    light (``voronoi``). Returns lights (N, 3) and shares (N, 3), rows summing to 1.

    README ("Where the error comes from"): tried on the development case surprise@cam0 against the
    Voronoi cells, +1–4 dB on the captured eye highlights but −0.4 dB on the skin; not the default.
    """
    from scipy.spatial import ConvexHull, QhullError

    samples = np.asarray(samples, np.float64)
    d = np.asarray(directions, np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    idx = np.zeros((len(samples), 3), np.int64)
    shares = np.zeros((len(samples), 3))
    found = np.zeros(len(samples), bool)
    try:
        hull = ConvexHull(d) if len(d) >= 4 else None
    except QhullError:   # all on one plane: no triangulation of the sphere
        hull = None
    if hull is not None:
        inside = hull.equations[:, 3] < -1e-9                           # n·x + offset <= 0: centre inside
        tri, eq = hull.simplices[inside], hull.equations[inside]
        inv = np.linalg.inv(np.transpose(d[tri], (0, 2, 1)))           # x = inv([a b c]) ω
        planes, plane = np.unique(np.round(eq, 9), axis=0, return_inverse=True)
        plane = plane.reshape(-1)
        scale = planes[:, :3] / -planes[:, 3:]
        members = [np.flatnonzero(plane == k) for k in range(len(planes))]
        table = np.array([np.resize(m, max(map(len, members))) for m in members])   # (planes, K) facets
        for s in range(0, len(samples), chunk):
            q = samples[s:s + chunk]
            cand = table[np.argmax(q @ scale.T, axis=1)]                            # (n, K)
            xc = np.einsum("nkij,nj->nki", inv[cand], q)
            f = cand[np.arange(len(q)), np.argmax(xc.min(axis=2), axis=1)]
            x = np.einsum("nij,nj->ni", inv[f], q)
            ok = (x.min(axis=1) >= -1e-9 * np.abs(x).max(axis=1)) & (x.sum(axis=1) > 0)
            if not ok.all():   # (a plane split by rounding) every facet for these few
                f[~ok] = np.argmax(np.einsum("fij,nj->nfi", inv, q[~ok]).min(axis=2), axis=1)
                x = np.einsum("nij,nj->ni", inv[f], q)
                ok = (x.min(axis=1) >= -1e-9 * np.abs(x).max(axis=1)) & (x.sum(axis=1) > 0)
            x = np.clip(x, 0.0, None)
            idx[s:s + chunk] = tri[f]
            shares[s:s + chunk] = x / np.where(ok, x.sum(axis=1), 1.0)[:, None]
            found[s:s + chunk] = ok
    if not found.all():
        near, _ = voronoi_shares(samples[~found], d)
        idx[~found] = near
        shares[~found] = np.array([1.0, 0.0, 0.0])
    return idx, shares


#: environment → light-stage weights: name → rule(sample directions (N, 3), light directions (L, 3))
#: → (lights (N, k), shares (N, k)): which lights a sample of the sphere lights, with what share
#: (each row sums to 1). The first entry is the default.
LIGHT_BASIS_METHODS = {"voronoi": voronoi_shares, "hat": hat_shares}
DEFAULT_LIGHT_BASIS_METHOD = "voronoi"


def light_shares(samples: np.ndarray, directions: np.ndarray, method: str = DEFAULT_LIGHT_BASIS_METHOD):
    """The light basis rule ``method`` (:data:`LIGHT_BASIS_METHODS`) applied to sample directions (N, 3)
    and light directions (L, 3): lights (N, k) and shares (N, k)."""
    from .methods import lookup

    return lookup(LIGHT_BASIS_METHODS, method, "light basis")(np.asarray(samples, np.float64), directions)


def light_basis(source, directions: np.ndarray, n_theta: int = 512,
                method: str = DEFAULT_LIGHT_BASIS_METHOD) -> np.ndarray:
    """Reduce a lighting environment to light-stage weights (L, 3): ``L_l = ∫ E(ω) h_l(ω) dω``.

    ``h_l`` is light l's share of direction ω under the rule ``method`` (:data:`LIGHT_BASIS_METHODS`):
    by default ``voronoi``, 1 inside the light's spherical-Voronoi cell (``L_l = ∫_{cell l} E dω``).
    ``source``: an :class:`Environment`, or any Mitsuba emitter that can be evaluated by
    direction (envmap, constant, sunsky …). ``directions``: (L, 3) light directions
    (world, towards the lights). The sphere is supersampled on an ``n_theta`` x
    ``2 n_theta`` lat-long grid with exact cell solid angles, each sample shared among its
    lights by the rule.
    """
    directions = np.asarray(directions, np.float64)
    qd, qw = sphere_quadrature(n_theta)
    if isinstance(source, Environment):
        mi = _mi()
        emitter = mi.load_dict(source.mitsuba_dict())
    else:
        emitter = source
    rad = evaluate_emitter(emitter, qd).astype(np.float64)
    if not np.isfinite(rad).all():
        raise EnvironmentError_("the environment evaluates to NaN/Inf radiance")
    lights, shares = light_shares(qd, directions, method)
    out = np.zeros((len(directions), 3))
    for k in range(lights.shape[1]):
        np.add.at(out, lights[:, k], rad * (qw * shares[:, k])[:, None])
    return out


def relight(olat: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Σ_l weights[l] · olat[l]: (L, H, W, 3) images and (L, 3) RGB weights → (H, W, 3)."""
    return np.einsum("lhwc,lc->hwc", olat, weights, optimize=True)


# ---------------------------------------------------- generated environments
def _sky(height: int, sun: bool) -> Environment:
    """Mitsuba's ``sunsky`` (Hosek–Wilkie sky, turbidity 3) baked to a lat-long map.

    Mitsuba's sky is Z-up; ``to_world`` turns it Y-up. Below the horizon: a ground of
    albedo 0.3 lit by the sky. The sun (0.53° wide, far smaller than a texel) is
    painted as a small disc with the sun's exact power, so energy is conserved.
    The map is scaled to a mean radiance of 0.5.
    """
    mi = _mi()
    sun_dir = np.array([0.45, 0.62, 0.64])
    sun_dir /= np.linalg.norm(sun_dir)
    base = {"type": "sunsky", "sun_direction": sun_dir.tolist(), "turbidity": 3.0, "albedo": 0.3,
            "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90)}
    dirs, sa = latlong_grid(height)
    rad = evaluate_emitter(mi.load_dict({**base, "sun_scale": 0.0}), dirs.reshape(-1, 3))
    rad = rad.reshape(height, 2 * height, 3).astype(np.float64)
    below = dirs[..., 1] < 0
    irradiance_up = (rad * np.clip(dirs[..., 1:2], 0, None) * sa[..., None]).sum(axis=(0, 1))
    rad[below] = 0.3 / np.pi * irradiance_up
    if sun:
        sun_emitter = mi.load_dict({**base, "sky_scale": 0.0})
        sun_radiance = evaluate_emitter(sun_emitter, sun_dir[None])[0].astype(np.float64)
        aperture = np.radians(0.5358)
        sun_power = sun_radiance * 2 * np.pi * (1 - np.cos(aperture / 2))
        footprint = np.exp(-0.5 * (np.arccos(np.clip(dirs @ sun_dir, -1, 1)) / (1.5 * np.pi / height)) ** 2)
        footprint /= (footprint * sa).sum()
        rad += footprint[..., None] * sun_power
    return Environment(rad * (0.5 / max(rad.mean(), 1e-12)), "sunsky" if sun else "sky")


def _interior(height: int) -> Environment:
    dirs, _ = latlong_grid(height)
    y = dirs[..., 1]
    wall = np.array([0.20, 0.17, 0.13]) * (0.7 + 0.3 * y[..., None])
    floor = np.array([0.10, 0.07, 0.05])
    ceiling = np.array([0.30, 0.30, 0.28])
    rad = np.where(y[..., None] < -0.2, floor, np.where(y[..., None] > 0.8, ceiling, wall))
    windows = [  # (centre direction, half-size in radians (yaw, pitch), radiance)
        (np.array([0.7, 0.25, 0.65]), (0.25, 0.30), np.array([9.0, 8.8, 8.0])),
        (np.array([-0.9, 0.2, -0.1]), (0.18, 0.35), np.array([5.0, 5.5, 6.5])),
        (np.array([0.0, 0.95, 0.3]), (0.20, 0.20), np.array([4.0, 4.0, 3.8])),
    ]
    for c, (hy, hp), radiance in windows:
        c = c / np.linalg.norm(c)
        up = np.array([0.0, 1.0, 0.0]) if abs(c[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
        right = np.cross(up, c)
        right /= np.linalg.norm(right)
        top = np.cross(c, right)
        a = np.arctan2(dirs @ right, dirs @ c)
        b = np.arctan2(dirs @ top, dirs @ c)
        inside = (np.abs(a) < hy) & (np.abs(b) < hp) & ((dirs @ c) > 0)
        rad = np.where(inside[..., None], radiance, rad)
    return Environment(rad, "interior")


def _gradient(height: int) -> Environment:
    dirs, _ = latlong_grid(height)
    y = dirs[..., 1:2]
    top = np.array([0.15, 0.35, 1.2])
    horizon = np.array([1.3, 0.7, 0.35])
    ground = np.array([0.25, 0.15, 0.08])
    sky = horizon + (top - horizon) * np.sqrt(np.clip(y, 0, 1))
    gnd = horizon * 0.4 + (ground - horizon * 0.4) * np.sqrt(np.clip(-y, 0, 1))
    rad = np.where(y >= 0, sky, gnd)
    # a slow colour shift around the vertical axis: warmer towards +X
    rad = rad * (1.0 + 0.35 * dirs[..., 0:1] * np.array([1.0, 0.2, -0.8]))
    return Environment(np.clip(rad, 0, None), "gradient")


GENERATORS = {"sky": lambda h: _sky(h, sun=False), "sunsky": lambda h: _sky(h, sun=True),
              "interior": _interior, "gradient": _gradient}


def cache_dir() -> Path:
    """Where generated data is cached: the user's cache (:func:`.formats.files.user_cache_dir`)."""
    from .formats.files import user_cache_dir

    return user_cache_dir()


def generated(name: str, height: int = 128) -> Environment:
    """A generated environment by name (sky, sunsky, interior, gradient), cached as EXR."""
    if name not in GENERATORS:
        raise ValueError(f"unknown generated environment {name!r}; choose one of {', '.join(GENERATORS)}")
    path = cache_dir() / "environments" / f"{name}-{height}.exr"
    if path.exists():
        try:
            return Environment.load(path)
        except Exception:
            path.unlink()
    env = GENERATORS[name](height)
    path.parent.mkdir(parents=True, exist_ok=True)
    env.save(path)
    return env


def resolve(spec: str, height: int = 128) -> Environment:
    """An environment from a generated name or a path to a lat-long .exr/.hdr."""
    if spec in GENERATORS:
        return generated(spec, height)
    return Environment.load(spec)
