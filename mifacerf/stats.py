"""Robust summaries of error arrays for reports (median, 95th percentile).

Units are those of the input; non-finite values (NaN for "not measured", ±inf) are ignored.
"""
from __future__ import annotations

import numpy as np


def median_p95(x, *, digits: int | None = 4, with_max: bool = False) -> dict:
    """Median and 95th percentile of the finite values of ``x`` (any shape).

    Returns ``{"median", "p95"}`` as Python floats rounded to ``digits`` decimals (``digits=None``:
    unrounded); both ``None`` when no value is finite. With ``with_max`` the dict also has ``"max"``
    (rounded likewise) and ``"n"`` (the number of finite values); when nothing is finite it is
    ``{"median": None, "p95": None, "n": 0}``.
    """
    x = np.asarray(x, np.float64).ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"median": None, "p95": None, "n": 0} if with_max else {"median": None, "p95": None}

    def r(v):
        return float(v) if digits is None else round(float(v), digits)

    out = {"median": r(np.median(x)), "p95": r(np.percentile(x, 95))}
    if with_max:
        out.update(max=r(x.max()), n=int(x.size))
    return out
