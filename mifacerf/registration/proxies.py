"""Lighting-independent image proxies (paper §4), cached next to the capture.

For every (expression, camera) two images are made from the reflectance field:

* **diffuse** — "completely diffuse lighting, except omitting a cone of lighting
  directions opposite from the camera, which largely eliminates bright glancing
  specularities": ``Σ_l Ω_l f_l`` over the lights whose direction makes more than
  ``cone`` with the direction *away from* the camera (``-ĉ``, ``ĉ`` the unit vector from
  the stage centre to the camera); ``Ω_l`` the light's solid angle, ``f_l`` the
  calibrated image (radiance per unit irradiance), so the result is the radiance under a
  uniform unit-radiance environment with that cone masked out. Each camera omits its
  own cone, so no single lighting could produce the set.
* **p95** — "each pixel represents the 95th percentile of brightness (over the
  varying lighting directions)", per channel (nearest rank), which removes the
  eyeball's specular highlights and most of the shadowing near the eyelids.

Both are float32 (H, W, 3) linear sRGB. The cache is
``CAPTURE/cache/<expression>/<camera>.proxies.npz`` with the cone angle and a stamp of
the source images (sizes, modification times and calibration); a stale or corrupt
cache is recomputed.
"""
from __future__ import annotations

import hashlib
import json
import warnings
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..formats.capture import Capture
from ..formats.files import save_npz_atomic
from ..rig import LightStage

DEFAULT_CONE_DEG = 60.0
PERCENTILE = 95.0


@dataclass
class Proxies:
    """``diffuse`` (H, W, 3), ``p95`` (H, W, 3), float32."""

    diffuse: np.ndarray
    p95: np.ndarray


def cone_weights(lights: LightStage, camera: Camera, cone_deg: float = DEFAULT_CONE_DEG) -> np.ndarray:
    """(L,) weights of the diffuse proxy: the solid angle, 0 inside the cone opposite the camera."""
    c = camera.centre / max(np.linalg.norm(camera.centre), 1e-12)
    cos_away = lights.directions @ (-c)
    keep = cos_away < np.cos(np.radians(cone_deg))
    return np.where(keep, lights.solid_angles, 0.0)


def percentile_image(field: np.ndarray, q: float = PERCENTILE) -> np.ndarray:
    """Per-pixel, per-channel ``q``-th percentile over lights (nearest rank) of (L, H, W, 3)."""
    L = field.shape[0]
    k = int(np.clip(round(q / 100.0 * (L - 1)), 0, L - 1))
    return np.partition(np.asarray(field), k, axis=0)[k].astype(np.float32)


def compute_proxies(field: np.ndarray, lights: LightStage, camera: Camera,
                    cone_deg: float = DEFAULT_CONE_DEG) -> Proxies:
    """Both proxies of one reflectance field (L, H, W, 3)."""
    w = cone_weights(lights, camera, cone_deg).astype(np.float32)
    diffuse = np.tensordot(w, np.asarray(field, np.float32), axes=(0, 0)).astype(np.float32)
    return Proxies(diffuse, percentile_image(field))


def _stamp(capture: Capture, expression: str, camera: str, cone_deg: float) -> str:
    stamp = capture._cache_stamp(expression, camera)
    data = json.dumps([stamp, capture._calibration_key(camera), cone_deg, PERCENTILE])
    return hashlib.sha1(data.encode()).hexdigest()


def proxy_path(capture: Capture, expression: str, camera: str) -> Path:
    return capture.root / "cache" / expression / f"{camera}.proxies.npz"


def load_cached(capture: Capture, expression: str, camera: str,
                cone_deg: float = DEFAULT_CONE_DEG) -> Proxies | None:
    """The cached proxies if present and current, else None."""
    path = proxy_path(capture, expression, camera)
    if not path.exists():
        return None
    try:
        z = np.load(path)
        if str(z["stamp"]) != _stamp(capture, expression, camera, cone_deg):
            return None
        return Proxies(z["diffuse"].astype(np.float32), z["p95"].astype(np.float32))
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile) as exc:   # a damaged cache is recomputed
        warnings.warn(f"{path}: damaged cache file ({type(exc).__name__}: {exc}); recomputed", stacklevel=2)
        return None


def save_cached(capture: Capture, expression: str, camera: str, proxies: Proxies,
                cone_deg: float = DEFAULT_CONE_DEG) -> Path:
    path = proxy_path(capture, expression, camera)
    save_npz_atomic(path, compressed=False, diffuse=proxies.diffuse, p95=proxies.p95,    # unique temporary name:
                    stamp=np.array(_stamp(capture, expression, camera, cone_deg)))     # concurrent runs may both save
    return path


def proxies_for(capture: Capture, expression: str, camera: str, field: np.ndarray | None = None,
                cone_deg: float = DEFAULT_CONE_DEG) -> Proxies:
    """Cached proxies of (expression, camera), computed (from ``field`` when given) and cached if needed."""
    p = load_cached(capture, expression, camera, cone_deg)
    if p is not None:
        return p
    if field is None:
        field = capture.field(expression, camera)
    p = compute_proxies(field, capture.rig.lights, capture.rig.camera(camera), cone_deg)
    save_cached(capture, expression, camera, p, cone_deg)
    return p
