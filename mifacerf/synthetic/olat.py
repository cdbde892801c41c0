"""Batched one-light-at-a-time (OLAT) rendering: the simulated light stage's photographs.

For one camera, the primary rays are traced once; then, for batches of lights, one
Dr.Jit wavefront evaluates every (surface sample × light) pair: the scene's own
Mitsuba BSDF (``bsdf.eval``, which includes the cosine) times the light's irradiance,
masked by a ray-traced shadow test. This is exactly what Mitsuba's ``direct``/``path``
integrators (max_depth = 2) compute for a directional emitter, without one
``mi.render`` call per light.

Light transport (the same for the path-traced ground truth in
:mod:`mifacerf.synthetic.truth`): direct illumination with ray-traced shadows;
interreflection and subsurface scattering are not simulated.

Pixel filter: box; ``spp`` stratified samples per pixel (:func:`mifacerf.camera.stratified_pixel_samples`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..jitarrays import from_jit, to_jit
from ..camera import Camera, stratified_pixel_samples
from ..variant import ensure_variant


@dataclass
class PrimaryHits:
    """The primary-ray hits of one camera, compacted to the samples that hit something.

    ``si``: Mitsuba SurfaceInteraction3f of width N (valid hits only); ``pixel``: (N,)
    flat pixel index of each sample; ``coverage``: (H, W) fraction of each pixel's
    samples that hit; ``shape``: (H, W); ``spp``.
    """

    si: object
    pixel: np.ndarray
    coverage: np.ndarray
    shape: tuple[int, int]
    spp: int

    def __len__(self) -> int:
        return len(self.pixel)


def camera_rays(camera: Camera, spp: int, seed: int = 0):
    """Mitsuba rays (width H*W*spp, world frame) for a camera's stratified pixel samples."""
    mi = ensure_variant()
    uv = stratified_pixel_samples(camera.width, camera.height, spp, seed)
    o, d = camera.pixel_rays(uv)
    origin = to_jit(mi.Point3f, np.repeat(np.asarray(o, np.float32)[:, None], len(d), axis=1))
    return mi.Ray3f(origin, to_jit(mi.Vector3f, d.T))


def primary_hits(scene, camera: Camera, spp: int = 4, seed: int = 0) -> PrimaryHits:
    """Trace a camera's primary rays once and keep the samples that hit the scene."""
    import drjit as dr

    mi = ensure_variant()
    ray = camera_rays(camera, spp, seed)
    si = scene.ray_intersect(ray)
    valid = np.asarray(si.is_valid()).astype(bool)
    idx = np.flatnonzero(valid).astype(np.uint32)
    si_c = dr.gather(mi.SurfaceInteraction3f, si, to_jit(mi.UInt32, idx))
    dr.eval(si_c)
    pixel = (idx // spp).astype(np.int64)
    h, w = camera.height, camera.width
    coverage = np.bincount(pixel, minlength=h * w).reshape(h, w) / spp
    return PrimaryHits(si_c, pixel, coverage, (h, w), spp)


def _batch_radiance(scene, hits: PrimaryHits, dirs: np.ndarray) -> np.ndarray:
    """(N*B, 3) radiance of every (sample, light) pair for unit-irradiance lights ``dirs`` (B, 3)."""
    import drjit as dr

    mi = ensure_variant()
    n, b = len(hits), len(dirs)
    lane = dr.arange(mi.UInt32, n * b)
    s_i = lane // b
    l_i = lane - s_i * b
    si = dr.gather(mi.SurfaceInteraction3f, hits.si, s_i)
    wi = dr.gather(mi.Vector3f, to_jit(mi.Vector3f, dirs.T), l_i)
    bsdf = si.bsdf()
    value = bsdf.eval(mi.BSDFContext(), si, si.to_local(wi))
    lit = ~scene.ray_test(si.spawn_ray(wi))
    value = dr.select(lit, value, 0.0)
    return from_jit(value)


def render_olat(scene, camera: Camera, directions: np.ndarray, irradiance: np.ndarray | None = None,
                spp: int = 4, seed: int = 0, max_lanes: int = 1 << 20, hits: PrimaryHits | None = None,
                on_batch=None) -> np.ndarray:
    """OLAT images of ``scene`` seen by ``camera``: (L, H, W, 3) float32.

    ``directions`` (L, 3): world unit vectors towards the lights (directional lights).
    ``irradiance`` (L, 3) RGB irradiance per light (default 1: radiance per unit
    irradiance). Lights are evaluated in batches of about ``max_lanes / N`` per Dr.Jit
    wavefront. ``on_batch(n_done)`` is called after each batch (progress bars).
    Background pixels are 0; partially covered pixels hold the coverage-weighted mean.
    """
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    n_lights = len(directions)
    irr = np.ones((n_lights, 3)) if irradiance is None else np.asarray(irradiance, np.float64).reshape(n_lights, 3)
    hits = primary_hits(scene, camera, spp, seed) if hits is None else hits
    h, w = hits.shape
    out = np.zeros((n_lights, h * w, 3), np.float32)
    if len(hits) == 0:
        return out.reshape(n_lights, h, w, 3)
    batch = max(1, min(n_lights, max_lanes // max(len(hits), 1)))
    for start in range(0, n_lights, batch):
        dirs = directions[start:start + batch]
        rad = _batch_radiance(scene, hits, dirs).reshape(len(hits), len(dirs), 3)
        for k in range(len(dirs)):
            for c in range(3):
                out[start + k, :, c] = np.bincount(hits.pixel, weights=rad[:, k, c], minlength=h * w)
        if on_batch is not None:
            on_batch(min(start + batch, n_lights))
    out /= hits.spp
    out *= irr[:, None, :].astype(np.float32)
    return out.reshape(n_lights, h, w, 3)
