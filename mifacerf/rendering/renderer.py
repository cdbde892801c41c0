"""The exact environment-lit renderer of a model (paper §6): target → RGBA image.

Per frame (:func:`.chunks.plan_frame` gives the render chunks):

1. the target mesh (template topology, world) is ray cast from the render camera
   (``spp`` stratified samples per pixel, box filter) → per sample a triangle and
   barycentrics;
2. per chunk (source ``s``, capture camera ``c``): the field's texels are lit with the
   per-vertex rotated lighting (:func:`.relight.lit_texels`, a sum over all lights) into
   a lit image in camera ``c``'s pixels;
3. each sample maps to the same surface point in the source geometry,
   ``p_s = Σ b_k V_s[tri_k]``, projected into camera ``c`` (lens distortion included);
   the lit image is sampled there (bilinear), if ``p_s`` is not occluded in that view
   (depth test against the field's texel depths), with weight ``a(p) = Σ b_k a_{v_k}``;
4. per sample: Σ a·value / Σ a over the chunks (renormalised: occluded chunks drop
   out); a sample that no chunk sees falls back to the chunks without the depth test.

No shadow is ever traced for the skin: the reflectance fields hold their own
self-shadowing. Output: (H, W, 4) float32, linear sRGB premultiplied by coverage.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..environment import Environment
from .chunks import FramePlan, plan_frame
from .lighting import RotatedLightBasis
from .meshscene import MeshScene
from .relight import lit_texels, to_device_f16


@dataclass
class RenderStats:
    """What a render did: seconds per stage, chunks and texels processed, fields loaded."""

    times: dict = field(default_factory=dict)
    chunks: int = 0
    texels: int = 0
    fields_loaded: list = field(default_factory=list)
    fallback_samples: int = 0
    unseen_samples: int = 0

    def add_time(self, stage: str, seconds: float) -> None:
        self.times[stage] = self.times.get(stage, 0.0) + seconds


def bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Sample an (H, W, C) image at (N, 2) pixel positions (OpenCV convention); outside → 0."""
    h, w = image.shape[:2]
    x, y = uv[:, 0], uv[:, 1]
    x0 = np.floor(x).astype(np.int64)
    y0 = np.floor(y).astype(np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    out = np.zeros((len(uv), image.shape[2]), image.dtype)
    for dy, dx, wgt in ((0, 0, (1 - fx) * (1 - fy)), (0, 1, fx * (1 - fy)), (1, 0, (1 - fx) * fy), (1, 1, fx * fy)):
        yy, xx = y0 + dy, x0 + dx
        ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
        out[ok] += wgt[ok] * image[yy[ok], xx[ok]]
    return out


def min_depth_2x2(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Smallest texel depth among the 2x2 texels around each (N, 2) position; +inf outside."""
    h, w = depth.shape
    x0 = np.floor(uv[:, 0]).astype(np.int64)
    y0 = np.floor(uv[:, 1]).astype(np.int64)
    best = np.full(len(uv), np.inf, np.float32)
    for dy in (0, 1):
        for dx in (0, 1):
            yy, xx = y0 + dy, x0 + dx
            ok = (yy >= 0) & (yy < h) & (xx >= 0) & (xx < w)
            best[ok] = np.minimum(best[ok], depth[yy[ok], xx[ok]])
    return best


class Renderer:
    """Renders a :class:`~.model.Model` with the exact environment-lit path.

    ``depth_tolerance`` (m): how far behind a field's seen surface a point may lie and
    still count as visible in that field.
    """

    def __init__(self, model, depth_tolerance: float = 0.004):
        self.model = model
        self.depth_tolerance = depth_tolerance
        self._scene = MeshScene(model.vertices[model.expression_index(model.neutral)], model.triangles)
        self._bases: dict[int, tuple[Environment, RotatedLightBasis]] = {}
        self._device: dict[tuple[int, int], object] = {}

    # -------------------------------------------------------------- lighting
    def light_basis(self, env: Environment) -> RotatedLightBasis:
        key = id(env)
        if key not in self._bases or self._bases[key][0] is not env:
            self._bases[key] = (env, RotatedLightBasis(env, self.model.light_directions))
        return self._bases[key][1]

    def _device_rf(self, s: int, c: int, f):
        key = (s, c)
        if key not in self._device:
            self._device[key] = to_device_f16(np.asarray(f.rf))
        return self._device[key]

    # ----------------------------------------------------------------- render
    def render(self, target: np.ndarray, expression_weights: np.ndarray, camera: Camera, env: Environment,
               spp: int = 4, seed: int = 0, frame: int = 0, plan: FramePlan | None = None,
               stats: RenderStats | None = None) -> np.ndarray:
        """Render (H, W, 4) RGBA of the target (T, 3) with (T, S) expression weights under ``env``."""
        model = self.model
        stats = stats if stats is not None else RenderStats()
        t0 = time.perf_counter()
        if plan is None:
            plan = plan_frame(model, target, expression_weights, camera, frame)
        stats.add_time("plan", time.perf_counter() - t0)

        t0 = time.perf_counter()
        basis = self.light_basis(env)
        lighting = {}
        for s in plan.sources:
            used = plan.expression_weights[:, s] > 0
            L = np.zeros((model.n_vertices, model.n_lights, 3), np.float32)
            L[used] = basis.rotated(plan.rotations[s][used])
            lighting[s] = L
        stats.add_time("lighting", time.perf_counter() - t0)

        t0 = time.perf_counter()
        self._scene.set_vertices(plan.target)
        hits, _ = self._scene.render_hits(camera, spp, seed)
        idx = np.flatnonzero(hits.valid)
        tri, bary = hits.tri[idx], hits.bary[idx]
        tv = model.triangles[tri]  # (N, 3) vertex ids of each sample's triangle
        stats.add_time("trace", time.perf_counter() - t0)

        acc = np.zeros((len(idx), 3))
        wsum = np.zeros(len(idx))
        acc_nodepth = np.zeros((len(idx), 3))
        wsum_nodepth = np.zeros(len(idx))
        cam_centres = [c.centre for c in model.cameras]
        for chunk in plan.chunks:
            s, c = chunk.s, chunk.c
            t0 = time.perf_counter()
            a_samp = (bary * chunk.weights[tv]).sum(1)
            need = a_samp > 0
            if not need.any():
                continue
            f = model.field(s, c)
            if (f.expression, f.camera) not in stats.fields_loaded:
                stats.fields_loaded.append((f.expression, f.camera))
            stats.add_time("load", time.perf_counter() - t0)

            t0 = time.perf_counter()
            fv = model.triangles[f.tri]
            wt = f.bary * chunk.weights[fv]
            wsum_t = wt.sum(1)
            active = np.flatnonzero(wsum_t > 0)
            lit = lit_texels(self._device_rf(s, c, f), model.n_lights, active, fv[active],
                             wt[active] / wsum_t[active, None], lighting[s])
            cam = model.cameras[c]
            img = np.zeros((cam.height, cam.width, 4), np.float32)
            px = f.pixels[active]
            img[px[:, 0], px[:, 1], :3] = lit
            img[px[:, 0], px[:, 1], 3] = 1.0
            stats.chunks += 1
            stats.texels += len(active)
            stats.add_time("relight", time.perf_counter() - t0)

            t0 = time.perf_counter()
            sel = np.flatnonzero(need)
            p_s = np.einsum("nk,nkd->nd", bary[sel], model.vertices[s][tv[sel]])
            uv, _ = cam.project(p_s)
            dist = np.linalg.norm(p_s - cam_centres[c], axis=1)
            ok = np.all(np.isfinite(uv), axis=1)
            sel, uv, dist = sel[ok], uv[ok], dist[ok]
            sample = bilinear(img, uv)
            cov = sample[:, 3]
            good = cov > 1e-3
            sel, uv, dist, sample, cov = sel[good], uv[good], dist[good], sample[good], cov[good]
            value = sample[:, :3] / cov[:, None]
            a = a_samp[sel]
            acc_nodepth[sel] += a[:, None] * value
            wsum_nodepth[sel] += a
            seen = dist <= min_depth_2x2(f.depth_map(), uv) + self.depth_tolerance
            acc[sel[seen]] += a[seen, None] * value[seen]
            wsum[sel[seen]] += a[seen]
            stats.add_time("sample", time.perf_counter() - t0)

        t0 = time.perf_counter()
        fallback = (wsum <= 1e-9) & (wsum_nodepth > 1e-9)
        stats.fallback_samples += int(fallback.sum())
        acc[fallback], wsum[fallback] = acc_nodepth[fallback], wsum_nodepth[fallback]
        covered = wsum > 1e-9
        stats.unseen_samples += int((~covered).sum())
        colour = np.zeros((len(idx), 3))
        colour[covered] = acc[covered] / wsum[covered, None]
        h, w = camera.height, camera.width
        rgba = np.zeros((h * w, 4))
        pix = idx // spp
        for ch in range(3):
            rgba[:, ch] = np.bincount(pix, weights=colour[:, ch], minlength=h * w)
        rgba[:, 3] = np.bincount(pix, weights=covered.astype(np.float64), minlength=h * w)
        rgba /= spp
        stats.add_time("resolve", time.perf_counter() - t0)
        out = rgba.reshape(h, w, 4).astype(np.float32)
        if not np.isfinite(out).all():
            raise FloatingPointError("render produced NaN/Inf pixels")
        return out
