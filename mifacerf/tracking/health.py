"""Per-camera, per-frame health of a performance video: what tracking may use.

Real video goes wrong in a few ways, each detected from the data alone (no truth):

* ``missing`` — the camera dropped the frame (no file, or an unreadable one);
* ``duplicate`` — the camera repeated its previous frame (bit-identical pixels to the last frame
  it delivered; two real exposures never are);
* ``dark`` — the camera went dark (lens cap, power, a light failure): mean brightness below
  ``dark_ratio`` of the camera's running reference (median over its last good frames).

Only ``ok`` images are searched for dots; the others are marked in the track and reported.
"""
from __future__ import annotations

import hashlib
from collections import deque

import numpy as np

OK, MISSING, DUPLICATE, DARK = 0, 1, 2, 3
NAMES = {OK: "ok", MISSING: "missing", DUPLICATE: "duplicate", DARK: "dark"}


class CameraHealth:
    """Streaming health check of one camera's frames (call :meth:`check` in frame order)."""

    def __init__(self, dark_ratio: float = 0.25, history: int = 30):
        self.dark_ratio = dark_ratio
        self.last_hash: bytes | None = None
        self.levels: deque = deque(maxlen=history)

    def check(self, image: np.ndarray | None) -> int:
        if image is None:
            return MISSING
        h = hashlib.blake2b(np.ascontiguousarray(image).tobytes(), digest_size=16).digest()
        dup = h == self.last_hash
        self.last_hash = h
        if dup:
            return DUPLICATE
        level = float(np.mean(image))
        if self.levels and level < self.dark_ratio * float(np.median(self.levels)):
            return DARK
        if not np.isfinite(level) or level <= 0:
            return DARK
        self.levels.append(level)
        return OK
