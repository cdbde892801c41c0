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
self-shadowing. Output: (H, W, 4) float32, linear sRGB premultiplied by coverage.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from ..environment import Environment
from ..jitarrays import from_jit, to_jit
from ..variant import ensure_variant
from .chunks import FramePlan, plan_frame
from .frame import LitFrame
from .lighting import RotatedLightBasis
from .meshscene import MeshScene
from .compression import lit_texels_pca
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


class Renderer:
    """Renders a :class:`~.model.Model` with the exact environment-lit path.

    ``depth_tolerance`` (m): how far behind a field's seen surface a point may lie and
    still count as visible in that field.
    """

    def __init__(self, model, depth_tolerance: float = 0.004, method: str = "exact", rank: int = 8):
        if method not in ("exact", "pca"):
            raise ValueError(f"unknown render method {method!r}; choose 'exact' or 'pca'")
        self.model = model
        self.depth_tolerance = depth_tolerance
        self.method = method
        self.rank = rank
        self._scene = MeshScene(model.vertices[model.expression_index(model.neutral)], model.triangles)
        self._bases: dict[int, tuple[Environment, RotatedLightBasis]] = {}
        self._device: dict[tuple[int, int], object] = {}

    # -------------------------------------------------------------- lighting
    def light_basis(self, env: Environment) -> RotatedLightBasis:
        key = id(env)
        if key not in self._bases or self._bases[key][0] is not env:
            self._bases[key] = (env, RotatedLightBasis(env, self.model.light_directions))
        return self._bases[key][1]

    def _device_pca(self, s: int, c: int):
        key = ("pca", self.rank, s, c)
        if key not in self._device:
            comp = self.model.compressed_field(s, c, self.rank)
            self._device[key] = (comp, to_device_f16(comp["coeff"]))
        return self._device[key]

    def _device_rf(self, s: int, c: int, f):
        key = (s, c)
        if key not in self._device:
            self._device[key] = to_device_f16(np.asarray(f.rf))
        return self._device[key]

    # ----------------------------------------------------------------- frame
    def light_frame(self, plan: FramePlan, env: Environment, stats: RenderStats | None = None) -> LitFrame:
        """Lighting per (vertex, source) and the lit image of every chunk of ``plan``."""
        model = self.model
        stats = stats if stats is not None else RenderStats()
        t0 = time.perf_counter()
        basis = self.light_basis(env)
        lighting = {}
        for s in plan.sources:
            used = plan.expression_weights[:, s] > 0
            L = np.zeros((model.n_vertices, model.n_lights, 3), np.float32)
            L[used] = basis.rotated(plan.rotations[s][used])
            lighting[s] = L
        stats.add_time("lighting", time.perf_counter() - t0)
        chunks = []
        for chunk in plan.chunks:
            s, c = chunk.s, chunk.c
            t0 = time.perf_counter()
            f = model.field(s, c)  # the texel map (the memory-mapped exact data is not read for 'pca')
            if (f.expression, f.camera) not in stats.fields_loaded:
                stats.fields_loaded.append((f.expression, f.camera))
            data = self._device_rf(s, c, f) if self.method == "exact" else self._device_pca(s, c)
            stats.add_time("load", time.perf_counter() - t0)
            t0 = time.perf_counter()
            fv = model.triangles[f.tri]
            wt = f.bary * chunk.weights[fv]
            wsum_t = wt.sum(1)
            active = np.flatnonzero(wsum_t > 0)
            coef = wt[active] / wsum_t[active, None]
            if self.method == "exact":
                lit = lit_texels(data, model.n_lights, active, fv[active], coef, lighting[s])
            else:
                comp, dev = data
                m_v = np.einsum("vlc,lc->vc", lighting[s], comp["mean"])
                beta_v = np.einsum("vlc,klc->vkc", lighting[s], comp["basis"])
                lit = lit_texels_pca(dev, comp["basis"].shape[0], active, fv[active], coef, m_v, beta_v)
            cam = model.cameras[c]
            img = np.zeros((cam.height, cam.width, 4), np.float32)
            px = f.pixels[active]
            img[px[:, 0], px[:, 1], :3] = lit
            img[px[:, 0], px[:, 1], 3] = 1.0
            chunks.append({"s": s, "c": c, "weights": chunk.weights, "image": img, "depth": f.depth_map(),
                           "camera": cam})
            stats.chunks += 1
            stats.texels += len(active)
            stats.add_time("relight", time.perf_counter() - t0)
        sources = {s: model.vertices[s] for s in plan.sources}
        return LitFrame(plan.target, model.triangles, chunks, sources, self.depth_tolerance)

    # ----------------------------------------------------------------- render
    def render(self, target: np.ndarray, expression_weights: np.ndarray, camera: Camera, env: Environment,
               spp: int = 4, seed: int = 0, frame: int = 0, plan: FramePlan | None = None,
               stats: RenderStats | None = None) -> np.ndarray:
        """Render (H, W, 4) RGBA of the target (T, 3) with (T, S) expression weights under ``env``."""
        mi = ensure_variant()
        model = self.model
        stats = stats if stats is not None else RenderStats()
        t0 = time.perf_counter()
        if plan is None:
            plan = plan_frame(model, target, expression_weights, camera, frame)
        stats.add_time("plan", time.perf_counter() - t0)
        lit = self.light_frame(plan, env, stats)

        t0 = time.perf_counter()
        self._scene.set_vertices(plan.target)
        hits, _ = self._scene.render_hits(camera, spp, seed)
        idx = np.flatnonzero(hits.valid)
        stats.add_time("trace", time.perf_counter() - t0)

        t0 = time.perf_counter()
        colour, covered, fell_back = lit.shade(to_jit(mi.UInt32, hits.tri[idx]),
                                              to_jit(mi.Vector3f, hits.bary[idx].T))
        colour = from_jit(colour)
        covered = np.asarray(covered).astype(bool)
        stats.fallback_samples += int(np.asarray(fell_back).sum())
        stats.unseen_samples += int((~covered).sum())
        stats.add_time("shade", time.perf_counter() - t0)

        t0 = time.perf_counter()
        h, w = camera.height, camera.width
        rgba = np.zeros((h * w, 4))
        pix = idx // spp
        for ch in range(3):
            rgba[:, ch] = np.bincount(pix, weights=np.where(covered, colour[:, ch], 0.0), minlength=h * w)
        rgba[:, 3] = np.bincount(pix, weights=covered.astype(np.float64), minlength=h * w)
        rgba /= spp
        stats.add_time("resolve", time.perf_counter() - t0)
        out = rgba.reshape(h, w, 4).astype(np.float32)
        if not np.isfinite(out).all():
            raise FloatingPointError("render produced NaN/Inf pixels")
        return out
