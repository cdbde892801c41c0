"""Temporal coherence: is the driven performance free of scintillation? (paper §5.1, §7)

Two signals are measured frame to frame, for the render and for the ground truth alike:

* the **§5 blend weights** (T vertices × S source expressions per frame): per frame pair, the mean
  over vertices of the total-variation distance ``½ Σ_s |w_t − w_{t−1}|`` (0: nothing changed,
  1: a vertex switched to entirely different sources);
* the **rendered pixels**: the mean absolute change of linear RGB over the face pixels covered in
  both frames, relative to their mean brightness.

Motion changes both smoothly; scintillation (a weight popping between Delaunay cells, a dot's
jitter flickering through the blend) changes them back and forth. So besides the first difference
(``change``) the **second difference** ``|x_{t+1} − 2 x_t + x_{t−1}|`` (``flicker``) is reported,
and their ratio: for smooth motion sampled at 60 fps the second difference is a small fraction
of the first; for frame-to-frame noise it is about twice it.
"""
from __future__ import annotations

import numpy as np


def _summary(x) -> dict:
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"mean": None, "p95": None, "max": None}
    return {"mean": round(float(x.mean()), 6), "p95": round(float(np.percentile(x, 95)), 6),
            "max": round(float(x.max()), 6)}


def weight_changes(W: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: (change (N−1,), flicker (N−2,)) of per-vertex weights ``W`` (N, T, S)."""
    W = np.asarray(W, np.float64)
    d1 = 0.5 * np.abs(np.diff(W, axis=0)).sum(-1).mean(-1)
    d2 = 0.5 * np.abs(W[2:] - 2 * W[1:-1] + W[:-2]).sum(-1).mean(-1) if len(W) > 2 else np.zeros(0)
    return d1, d2


class PixelCoherence:
    """Streaming frame-to-frame change of images (feed frames in order with :meth:`add`)."""

    def __init__(self, coverage: float = 0.99):
        self.coverage = coverage
        self.frames: list = []      # the last three (rgb, mask)
        self.change: list = []
        self.flicker: list = []

    def add(self, rgba: np.ndarray) -> None:
        rgb = np.asarray(rgba[..., :3], np.float64)
        mask = np.asarray(rgba[..., 3]) >= self.coverage if rgba.shape[-1] == 4 else np.ones(rgb.shape[:2], bool)
        self.frames.append((rgb, mask))
        self.frames = self.frames[-3:]
        if len(self.frames) >= 2:
            (a, ma), (b, mb) = self.frames[-2:]
            m = ma & mb
            ref = max(float(np.abs(b[m]).mean()), 1e-12) if m.any() else np.nan
            self.change.append(float(np.abs(b - a)[m].mean()) / ref if m.any() else np.nan)
        if len(self.frames) == 3:
            (a, ma), (b, mb), (c, mc) = self.frames
            m = ma & mb & mc
            ref = max(float(np.abs(b[m]).mean()), 1e-12) if m.any() else np.nan
            self.flicker.append(float(np.abs(c - 2 * b + a)[m].mean()) / ref if m.any() else np.nan)

    def summary(self) -> dict:
        c, f = np.asarray(self.change), np.asarray(self.flicker)
        out = {"change": _summary(c), "flicker": _summary(f)}
        if c.size and f.size and np.nanmean(c) > 0:
            out["flicker_to_change"] = round(float(np.nanmean(f) / np.nanmean(c)), 4)
        return out


def weight_summary(W: np.ndarray) -> dict:
    d1, d2 = weight_changes(W)
    out = {"change": _summary(d1), "flicker": _summary(d2)}
    if d1.size and d2.size and d1.mean() > 0:
        out["flicker_to_change"] = round(float(d2.mean() / d1.mean()), 4)
    return out
