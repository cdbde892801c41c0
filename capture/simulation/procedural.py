"""A procedural stand-in subject: a textured, dotted ellipsoid "head", rendered analytically.

It exists so that the protocol, the sessions and their tests do not depend on the
full synthetic subject (:mod:`mifacerf.synthetic`): it is cheap (NumPy, no Mitsuba),
deterministic, and has what a capture check needs — smooth shading that changes
with the light, fine albedo texture and bright fiducial dots (paper §2.1) whose edges
blur when the subject moves.

Renderer interface (shared with the synthetic subject's adapter,
:mod:`mifacerf.capture.simulation.subject`)::

    render(expression, camera, lights) -> (len(lights), H, W, 3) float32

radiance in linear sRGB per unit irradiance (docs/conventions.md) of ``expression``
(a dict of parameters) seen by ``camera`` (:class:`mifacerf.camera.Camera`) under
each light of ``rig.lights`` (light indices, one image per light).
"""
from __future__ import annotations

import numpy as np

from ...camera import Camera
from ...rig import LightStage

SKIN = np.array([0.62, 0.42, 0.33])
DOT = np.array([0.85, 0.85, 0.10])  # fluorescent yellow gel-ink dots


class ProceduralHead:
    """An ellipsoid head (semi-axes ``axes`` metres, centred at ``centre`` in **world**) with
    Lambertian skin, a sinusoidal pore texture and fiducial dots; no cast shadows.

    Expression parameters (dict, all optional): ``jaw`` (0..1 lengthens the lower half),
    ``smile`` (-1..1 widens it), ``shift`` (3,) metres rigid translation of the head.
    """

    def __init__(self, lights: LightStage, *, axes=(0.075, 0.105, 0.09), centre=(0.0, 0.0, 0.0),
                 n_dots: int = 60, supersample: int = 2, seed: int = 0):
        self.lights = lights
        self.axes = np.asarray(axes, np.float64)
        self.centre = np.asarray(centre, np.float64)
        self.supersample = int(supersample)
        rng = np.random.default_rng(seed)
        d = rng.standard_normal((n_dots, 3))
        d[:, 2] = np.abs(d[:, 2]) + 0.3  # on the front of the face
        self.dots = d / np.linalg.norm(d, axis=1, keepdims=True)
        self.dot_radius = 0.06  # on the unit sphere (radians, roughly)
        self.tex_freq = rng.uniform(20, 45, size=(4, 3)) * rng.choice([-1, 1], size=(4, 3))
        self._rays: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}

    def _camera_rays(self, camera: Camera):
        key = (camera.name, camera.width, camera.height, camera.K.tobytes(), camera.dist.tobytes(),
               camera.R.tobytes(), camera.t.tobytes())
        if key not in self._rays:
            s = self.supersample
            off = (np.arange(s) + 0.5) / s - 0.5
            jj, ii = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
            u = (jj[..., None, None] + off[None, None, None, :]).repeat(s, axis=2)
            v = (ii[..., None, None] + off[None, None, :, None]).repeat(s, axis=3)
            uv = np.stack([u, v], axis=-1).reshape(-1, 2)
            self._rays[key] = camera.pixel_rays(uv)
        return self._rays[key]

    def geometry(self, expression: dict, camera: Camera):
        """Per sample: (hit mask (N,), world normals (N, 3), albedo (N, 3))."""
        origin, d = self._camera_rays(camera)
        axes = self.axes.copy()
        jaw, smile = float(expression.get("jaw", 0.0)), float(expression.get("smile", 0.0))
        centre = self.centre + np.asarray(expression.get("shift", (0.0, 0.0, 0.0)), np.float64)
        o = (origin - centre)[None, :]
        # lower half stretched by the jaw: intersect the two half-ellipsoids, keep the nearer valid hit
        best_t = np.full(len(d), np.inf)
        best_p = np.zeros_like(d)
        best_ax = np.zeros_like(d)
        for lower in (False, True):
            ax = axes * np.array([1 + 0.15 * smile if lower else 1.0, 1 + 0.25 * jaw if lower else 1.0, 1.0])
            oo, dd = o / ax, d / ax
            a = np.sum(dd * dd, axis=1)
            b = 2 * np.sum(oo * dd, axis=1)
            c = np.sum(oo * oo, axis=1) - 1
            disc = b * b - 4 * a * c
            ok = disc > 0
            t = np.where(ok, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
            p = o + t[:, None] * d
            valid = ok & (t > 0) & ((p[:, 1] < 0) == lower) & (t < best_t)
            best_t = np.where(valid, t, best_t)
            best_p[valid] = p[valid]
            best_ax[valid] = ax
        hit = np.isfinite(best_t)
        ax = np.where(hit[:, None], best_ax, 1.0)
        n = best_p / ax**2
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        q = best_p / ax  # on the unit sphere: texture coordinates that move with the skin
        tex = 1 + 0.12 * np.sum(np.sin(q @ self.tex_freq.T), axis=1) / 2
        albedo = SKIN[None, :] * tex[:, None]
        on_dot = (q @ self.dots.T).max(axis=1) > np.cos(self.dot_radius)
        albedo[on_dot] = DOT
        mouth = (np.abs(q[:, 1] + 0.45) < 0.05 + 0.25 * jaw) & (np.abs(q[:, 0]) < 0.35 + 0.1 * smile) & (q[:, 2] > 0)
        albedo[mouth] *= 0.25
        return hit, n, albedo

    def render(self, expression: dict, camera: Camera, lights) -> np.ndarray:
        """(len(lights), H, W, 3) float32 radiance per unit irradiance (black background)."""
        lights = np.asarray(lights, np.int64).reshape(-1)
        hit, n, albedo = self.geometry(expression, camera)
        cos = np.clip(n @ self.lights.directions[lights].T, 0.0, None) * hit[:, None]  # (N, L)
        img = (cos.T[:, :, None] * albedo[None] / np.pi).astype(np.float32)  # (L, N, 3)
        s = self.supersample
        img = img.reshape(len(lights), camera.height, camera.width, s, s, 3).mean(axis=(3, 4))
        return img


def default_expression_params(name: str, index: int) -> dict:
    """Deterministic parameters for a named expression (stand-in subject)."""
    rng = np.random.default_rng(index + 1)
    if name == "neutral":
        return {"jaw": 0.0, "smile": 0.0}
    return {"jaw": float(rng.uniform(0, 1)), "smile": float(rng.uniform(-1, 1))}
