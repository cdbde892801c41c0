"""Camera response curves by Debevec & Malik (1997), "Recovering high dynamic range radiance
maps from photographs" — generalised to a lit grey chart (paper §2.1).

Every measurement is a recorded value ``z`` of something whose linear value is a
product ``a_i * b_j``: in the classic method ``a_i`` is an unknown scene radiance and
``b_j`` a known exposure time; for a light stage's *lighting dataset of a grayscale
chart* ``a_i`` is the unknown irradiance of light ``i`` on the chart and ``b_j`` the
known reflectance of grey patch ``j``. With ``g = ln f^-1`` (``f`` the response):

    g(z_ij) = ln a_i + ln b_j

is linear in the unknowns: ``g`` at ``n_knots`` knots (piecewise linear in z) and the
unknown logs. Least squares, weighted by a hat function of z (the ends of the range
are noisy or clipped), with a second-difference smoothness penalty ``smoothness``;
the scale is fixed by ``g(z_ref) = 0``. The recovered ``f^-1`` is made monotone and
returned as a curve ``{"x": recorded, "y": linear}`` for
:class:`mifacerf.formats.capture.Radiometry`, normalised so ``y = 1`` at ``x = 1``.
"""
from __future__ import annotations

import numpy as np
from ...errors import MifacerfError


class ResponseError(MifacerfError, ValueError):
    """Not enough usable measurements to recover a response curve."""


def hat(z: np.ndarray, lo: float = 0.0, hi: float = 1.0) -> np.ndarray:
    """Debevec's weighting: 0 at the ends of [lo, hi], 1 in the middle (with a small floor)."""
    mid = (lo + hi) / 2
    w = np.where(z <= mid, z - lo, hi - z) / (mid - lo)
    return np.clip(w, 0.0, 1.0) + 1e-3


def recover_response(z: np.ndarray, log_known: np.ndarray, known_axis: int = 1, *, n_knots: int = 33,
                     smoothness: float = 1.0, z_range=(0.0, 1.0), z_ref: float = 0.5,
                     min_weight: float = 0.02) -> dict:
    """Recover ``f^-1`` from measurements ``z`` (I, J) — NaN where missing.

    ``log_known``: the known logs along ``known_axis`` (J values for axis 1: patch
    reflectances or exposure times); the other axis is unknown. Returns
    ``{"x", "y", "log_unknown", "residual_rms"}``.
    """
    z = np.asarray(z, np.float64)
    if z.ndim != 2:
        raise ResponseError(f"expected measurements (I, J), got shape {z.shape}")
    if known_axis == 0:
        z = z.T
    n_i, n_j = z.shape
    log_known = np.asarray(log_known, np.float64).reshape(-1)
    if len(log_known) != n_j:
        raise ResponseError(f"{len(log_known)} known values for {n_j} columns")
    lo, hi = z_range
    # knots denser at the dark end, where ln f^-1 bends most; below z_floor no data is used
    z_floor = lo + 0.01 * (hi - lo)
    knots = z_floor + (hi - z_floor) * np.linspace(0.0, 1.0, n_knots) ** 2
    ii, jj = np.nonzero(np.isfinite(z))
    zz = z[ii, jj]
    w = hat(zz, lo, hi)
    use = (w > min_weight) & (zz > z_floor)
    ii, jj, zz, w = ii[use], jj[use], zz[use], w[use]
    rows_with_data = np.unique(ii)
    if len(zz) < n_knots or len(rows_with_data) < 2:
        raise ResponseError(f"only {len(zz)} usable measurements in {len(rows_with_data)} image(s); need more "
                            "images with the chart well exposed")
    # unknowns: g at knots (n_knots), ln a_i (n_i)
    k0 = np.clip(np.searchsorted(knots, zz, side="right") - 1, 0, n_knots - 2)
    f = (zz - knots[k0]) / (knots[k0 + 1] - knots[k0])
    n_un = n_knots + n_i
    rows, cols, vals, rhs = [], [], [], []
    r = 0
    for m in range(len(zz)):
        rows += [r, r, r]
        cols += [k0[m], k0[m] + 1, n_knots + ii[m]]
        vals += [w[m] * (1 - f[m]), w[m] * f[m], -w[m]]
        rhs.append(w[m] * log_known[jj[m]])
        r += 1
    # smoothness: second derivative of g (non-uniform knots), scaled with the data's weight
    lam = smoothness * np.sqrt(len(zz) / n_knots)
    h = np.diff(knots)
    for k in range(1, n_knots - 1):
        a, b = 1 / h[k - 1], 1 / h[k]
        s_k = lam * (h[k - 1] + h[k]) / 2 * np.mean(h)  # scale-free: comparable across knots
        rows += [r, r, r]
        cols += [k - 1, k, k + 1]
        vals += [s_k * a, -s_k * (a + b), s_k * b]
        rhs.append(0.0)
        r += 1
    # gauge: g(z_ref) = 0
    kr = int(np.clip(np.searchsorted(knots, z_ref, side="right") - 1, 0, n_knots - 2))
    fr = (z_ref - knots[kr]) / (knots[kr + 1] - knots[kr])
    rows += [r, r]
    cols += [kr, kr + 1]
    vals += [10 * (1 - fr), 10 * fr]
    rhs.append(0.0)
    r += 1
    # rows that no measurement touches would be free: tie their unknown to 0
    for i in set(range(n_i)) - set(rows_with_data.tolist()):
        rows.append(r)
        cols.append(n_knots + i)
        vals.append(1e-3)
        rhs.append(0.0)
        r += 1
    from scipy.sparse import csr_matrix

    A = csr_matrix((vals, (rows, cols)), shape=(r, n_un)).toarray()  # small: knots + images columns
    sol = np.linalg.lstsq(A, np.asarray(rhs), rcond=None)[0]
    g = sol[:n_knots]
    log_a = sol[n_knots:]
    pred = (g[k0] * (1 - f) + g[k0 + 1] * f) - log_a[ii]
    resid = float(np.sqrt(np.mean((pred - log_known[jj]) ** 2)))
    # monotone, normalised curve; knots never reached by data are extrapolated by the smoothness term
    y = np.maximum.accumulate(np.exp(g - g[-1]))
    # below the first knot the curve runs straight to (lo, 0): recorded black is linear black
    x_out = np.concatenate([[lo], knots])
    y_out = np.concatenate([[0.0], y])
    y_out = y_out + np.linspace(0, 1e-9, len(y_out))  # strictly increasing
    return {"x": x_out.tolist(), "y": y_out.tolist(), "log_unknown": log_a.tolist(), "residual_rms": resid}


def apply_inverse(curve: dict, z: np.ndarray) -> np.ndarray:
    """Linearise recorded values ``z`` with a ``{"x", "y"}`` curve (as Radiometry does)."""
    return np.interp(np.asarray(z, np.float64), np.asarray(curve["x"]), np.asarray(curve["y"]))


def curve_error(curve: dict, true_inverse, x_range=(0.05, 0.95), n: int = 181) -> dict:
    """Relative error of a recovered ``f^-1`` against the truth (both normalised at x = 0.5):
    ``{"rms", "max"}`` over ``x_range``."""
    x = np.linspace(*x_range, n)
    est = apply_inverse(curve, x) / apply_inverse(curve, np.array([0.5]))[0]
    tru = np.asarray(true_inverse(x), np.float64) / float(np.asarray(true_inverse(np.array([0.5])))[0])
    rel = est / tru - 1
    return {"rms": float(np.sqrt(np.mean(rel ** 2))), "max": float(np.max(np.abs(rel)))}
