"""The images the studio shows, tone-mapped on the server into 8-bit PNGs (cached).

Kinds (per expression and camera), all calibrated radiance per unit irradiance (docs/capture-format.md):

* ``diffuse`` — the lighting-independent diffuse proxy (paper §4; :mod:`mifacerf.registration.proxies`);
* ``p95`` — the per-pixel 95th percentile over the lights (no eye highlights, little lid shadow);
* ``sum`` — the sum of all lights' images;
* ``light`` — one light's image (``light`` = its index);
* ``dots`` — the dot-strength map (1 = a typical, clearly seen dot), grey.

Tone mapping: ``v' = (v · 2^exposure / white)^(1/gamma)`` clipped to [0, 1], where ``white`` is the
99.5th percentile of the image's luminance (so exposure 0 shows any capture sensibly; the dot map
uses white = 1). Linear sRGB values are shown as if they were display values after the gamma (a
viewer, not a colour-managed export).
"""
from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

KINDS = ("diffuse", "p95", "sum", "light", "dots")


class LRU:
    """A small thread-safe least-recently-used cache."""

    def __init__(self, size: int):
        self.size = size
        self._d: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key):
        with self._lock:
            if key in self._d:
                self._d.move_to_end(key)
                return self._d[key]
        return None

    def put(self, key, value):
        with self._lock:
            self._d[key] = value
            self._d.move_to_end(key)
            while len(self._d) > self.size:
                self._d.popitem(last=False)
        return value

    def clear(self):
        with self._lock:
            self._d.clear()


def tone_map(img: np.ndarray, exposure: float = 0.0, gamma: float = 2.2, white: float | None = None) -> np.ndarray:
    """(H, W, 3) uint8 from a linear image (H, W, 3) or a map (H, W)."""
    img = np.asarray(img, np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
    if white is None:
        from ..imageio import LUMINANCE

        lum = img @ LUMINANCE.astype(np.float32)
        white = float(np.percentile(lum, 99.5)) if lum.size else 1.0
    white = max(white, 1e-12)
    gamma = float(np.clip(gamma, 0.2, 5.0))
    v = np.clip(img * np.float32(2.0 ** float(np.clip(exposure, -20, 20)) / white), 0.0, 1.0) ** np.float32(1.0 / gamma)
    return np.round(v * 255.0).astype(np.uint8)


def encode_png(rgb: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()
