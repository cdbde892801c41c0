"""Batched one-light-at-a-time (OLAT) rendering: the simulated light stage's photographs.

For one camera, the primary rays are traced once; then one Dr.Jit kernel loops over
all lights for every surface sample: the scene's own Mitsuba BSDF (``bsdf.eval``,
which includes the cosine) times the light's irradiance, masked by a ray-traced
shadow test. This is exactly what Mitsuba's ``direct``/``path``
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


def render_olat(scene, camera: Camera, directions: np.ndarray, irradiance: np.ndarray | None = None,
                spp: int = 4, seed: int = 0, hits: PrimaryHits | None = None, max_values: int = 1 << 28) -> np.ndarray:
    """OLAT images of ``scene`` seen by ``camera``: (L, H, W, 3) float32.

    ``directions`` (L, 3): world unit vectors towards the lights (directional lights).
    ``irradiance`` (L, 3) RGB irradiance per light (default 1: radiance per unit
    irradiance). One kernel per group of lights: a symbolic loop over the lights
    evaluates the BSDF at every surface sample and traces a shadow ray only where the
    BSDF is non-zero, adding each sample into its pixel (box filter). Background pixels
    are 0; partially covered pixels hold the coverage-weighted mean.
    """
    import drjit as dr

    mi = ensure_variant()
    directions = np.asarray(directions, np.float64).reshape(-1, 3)
    n_lights = len(directions)
    irr = np.ones((n_lights, 3)) if irradiance is None else np.asarray(irradiance, np.float64).reshape(n_lights, 3)
    hits = primary_hits(scene, camera, spp, seed) if hits is None else hits
    h, w = hits.shape
    hw = h * w
    out = np.zeros((n_lights, hw, 3), np.float32)
    n = len(hits)
    if n == 0 or n_lights == 0:
        return out.reshape(n_lights, h, w, 3)
    si = hits.si
    bsdf = si.bsdf()
    ctx = mi.BSDFContext()
    pix = to_jit(mi.UInt32, hits.pixel.astype(np.uint32))
    group = max(1, min(n_lights, max_values // (hw * 3)))
    for start in range(0, n_lights, group):
        dirs = directions[start:start + group]
        count = len(dirs)
        acc = dr.zeros(mi.Float, count * hw * 3)
        D = to_jit(mi.Vector3f, dirs.T)
        n_count = dr.opaque(mi.UInt32, count)

        def body(i):
            wi = dr.gather(mi.Vector3f, D, i)
            value = bsdf.eval(ctx, si, si.to_local(wi))
            nonzero = (value.x > 0) | (value.y > 0) | (value.z > 0)
            lit = nonzero & ~scene.ray_test(si.spawn_ray(wi), nonzero)
            base = (i * hw + pix) * 3
            for c in range(3):
                dr.scatter_reduce(dr.ReduceOp.Add, acc, value[c], base + c, lit)
            return (i + 1,)

        dr.while_loop((dr.opaque(mi.UInt32, 0, n),), lambda i: i < n_count, body)
        out[start:start + count] = np.asarray(acc).reshape(count, hw, 3)
    out /= hits.spp
    out *= irr[:, None, :].astype(np.float32)
    return out.reshape(n_lights, h, w, 3)
