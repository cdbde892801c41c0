"""Dots in the images of one camera: the tuned detector, the search about predictions, conflicts.

The detector is registration's linear dot filter (:class:`mifacerf.registration.dots.DotFilter`,
paper §4.1), tuned once on the performance itself — on the first frame every camera sees well,
where the subject is at rest and the template's fiducials project within a pixel or two of their
dots — so its colour direction, kernel size and per-camera scale fit the video's lighting and
resolution. A dot-strength of 1 is a typical, clearly seen dot.

Per frame and camera, every dot expected to be visible is searched for about its predicted pixel
position (:func:`search`): the local maximum of the strength map nearest to the prediction within
``radius`` pixels, refined to sub-pixel precision (parabola, then a Gaussian-windowed centroid),
accepted if its strength passes a threshold. Two dots may not take the same image dot (:func:`resolve_conflicts`:
the one predicted closer keeps it).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.maxima import maxima_points
from ..registration.dots import DotFilter, peak_near


@dataclass
class Detector:
    """The tuned dot filter and the centroid window (pixels)."""

    filter: DotFilter
    centroid_sigma: float

    @classmethod
    def tune(cls, images: dict, uv: dict, dot_radius_px: float) -> "Detector":
        """Tune on ``images`` {camera: (H, W, 3)} with the fiducials' expected pixels ``uv`` {camera: (N, 2)}."""
        f = DotFilter.fit(images, uv, dot_radius_px)
        return cls(f, max(1.0, 1.5 * f.sigma))

    def strength(self, image: np.ndarray, camera: str) -> np.ndarray:
        """Dot-strength map (H, W) of one image."""
        return self.filter.strength(image, camera)

    def to_dict(self) -> dict:
        return {"filter": self.filter.to_dict(), "centroid_sigma": self.centroid_sigma}


def search(strength: np.ndarray, predicted: np.ndarray, radius: float, threshold: float,
           centroid_sigma: float, maxima=None) -> tuple[np.ndarray, np.ndarray]:
    """Dots near predicted pixels (N, 2): (found (N, 2) with NaN where none, strength (N,)).

    The image dot of a prediction is the local maximum of the strength map *nearest* to it (not
    the strongest in a window: a brighter neighbouring dot must not win) within ``radius`` pixels,
    whose strength passes ``threshold``; its position is refined to sub-pixel precision.
    ``maxima``: precomputed :func:`mifacerf.geometry.maxima.maxima_points` of the float32 map (with a
    threshold ≤ this one).
    """
    from scipy.spatial import cKDTree

    pred = np.asarray(predicted, np.float64).reshape(-1, 2)
    out = np.full(pred.shape, np.nan)
    val = np.zeros(len(pred))
    ok = np.isfinite(pred).all(1)
    peaks, values = maxima if maxima is not None else maxima_points(np.asarray(strength, np.float32), threshold)
    keep = values >= threshold
    peaks = peaks[keep]
    if not ok.any() or len(peaks) == 0:
        return out, val
    dist, idx = cKDTree(peaks).query(pred[ok], distance_upper_bound=radius + 0.75)
    hit = np.isfinite(dist)
    rows = np.flatnonzero(ok)[hit]
    if len(rows) == 0:
        return out, val
    pk, v = peak_near(strength, peaks[idx[hit]], 0.5, centroid_sigma=centroid_sigma)
    good = np.isfinite(pk).all(1) & (v >= threshold) & (np.linalg.norm(pk - pred[rows], axis=1) <= radius * 1.05)
    out[rows[good]] = pk[good]
    val[rows[good]] = v[good]
    return out, val


def resolve_conflicts(found: np.ndarray, predicted: np.ndarray, min_separation: float) -> np.ndarray:
    """Boolean (N,) of found dots to drop: of two found within ``min_separation`` pixels of each other
    (one image dot claimed twice) the one whose prediction was farther loses."""
    from scipy.spatial import cKDTree

    found = np.asarray(found, np.float64)
    drop = np.zeros(len(found), bool)
    idx = np.flatnonzero(np.isfinite(found).all(1))
    if len(idx) < 2:
        return drop
    pairs = cKDTree(found[idx]).query_pairs(min_separation, output_type="ndarray")
    dist = np.linalg.norm(found - predicted, axis=1)
    for a, b in pairs:
        i, j = idx[a], idx[b]
        drop[i if dist[i] > dist[j] else j] = True
    return drop
