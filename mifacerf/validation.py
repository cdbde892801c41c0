"""Physical sense of captured radiance (ground floor): registration and build refuse images that
cannot be light.

A camera measures radiance: it is finite and non-negative. Noise and the calibration's black-level
subtraction can leave tiny negatives in dark pixels, so the rule has a tolerance:

* any NaN or ±Inf pixel is an error;
* a pixel below ``-NEGATIVE_TOLERANCE`` × the image's peak (its largest finite channel value, at least
  :data:`PEAK_FLOOR`) is an error — with the default 1e-3, a −5 patch in an image whose peak is 0.6 is
  refused while −1e-4 of noise is accepted.

The error names the file (or the expression, camera and light), the value and the tolerance.
"""
from __future__ import annotations

import numpy as np

from .errors import MifacerfError

#: a pixel below -NEGATIVE_TOLERANCE x the image's peak is not noise (docs/reliability.md)
NEGATIVE_TOLERANCE = 1e-3
#: the peak used for an all-dark image (so that its noise is judged against a sensible scale)
PEAK_FLOOR = 1e-3


class RadianceError(MifacerfError, ValueError):
    """Captured radiance that cannot be light: NaN, Inf or clearly negative pixels."""


def check_field(field: np.ndarray, expression: str, camera: str, path_of=None, lights=None) -> None:
    """Check a reflectance field (L, H, W, 3) of one (expression, camera); ``path_of(light)`` names the
    file of a light's image, ``lights`` the light index of each of the L images (default 0..L-1)."""
    f = np.asarray(field)
    if f.ndim != 4 or f.shape[0] == 0:
        return
    flat = f.reshape(f.shape[0], -1)
    # one pass for the max and one for the min of every image: a NaN propagates into both, +Inf into the
    # max, -Inf into the min, so an image holds a non-finite value exactly when one of them is not finite
    with np.errstate(invalid="ignore"):
        hi, lo = flat.max(axis=1), flat.min(axis=1)
    bad_finite = ~(np.isfinite(hi) & np.isfinite(lo))
    peak = np.maximum(hi, PEAK_FLOOR)
    low = lo
    if bad_finite.any():   # the finite values' peak and low of those images only
        rows = np.flatnonzero(bad_finite)
        finite = np.isfinite(flat[rows])
        with np.errstate(invalid="ignore"):
            peak[rows] = np.maximum(np.where(finite, flat[rows], -np.inf).max(axis=1), PEAK_FLOOR)
            low[rows] = np.where(finite, flat[rows], np.inf).min(axis=1)
    bad_negative = low < -NEGATIVE_TOLERANCE * peak
    bad = np.flatnonzero(bad_finite | bad_negative)
    if not bad.size:
        return
    i = int(bad[0])
    light = int(lights[i]) if lights is not None else i
    where = f"{path_of(light)} ({expression}, {camera}, light {light})" if path_of else \
        f"expression {expression}, camera {camera}, light {light}"
    more = f"; {bad.size - 1} more image(s) of this camera too" if bad.size > 1 else ""
    if bad_finite[i]:
        n = int((~np.isfinite(flat[i])).sum())
        raise RadianceError(f"{where}: {n} NaN/Inf pixel value(s): not radiance{more}")
    n = int((flat[i] < -NEGATIVE_TOLERANCE * peak[i]).sum())
    raise RadianceError(f"{where}: {n} pixel value(s) down to {float(low[i]):.4g}, below the tolerance "
                        f"-{NEGATIVE_TOLERANCE:g} x the image's peak {float(peak[i]):.4g}: negative radiance{more}")
