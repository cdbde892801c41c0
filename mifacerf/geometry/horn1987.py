"""Closed-form absolute orientation with unit quaternions (Horn 1987).

B. K. P. Horn, "Closed-form solution of absolute orientation using unit
quaternions", J. Opt. Soc. Am. A 4(4), 1987.  The paper (§5) aligns every local
neighbourhood with this method; rendering (§6.1) uses the same transform for the
local rotations ``R_ts``.

Given corresponding points ``P`` and ``Q`` (optionally weighted), the rotation
``R`` and translation ``t`` minimising ``sum_i w_i |R p_i + t - q_i|^2`` are:

* ``t = q̄ - R p̄`` with the weighted centroids ``p̄, q̄``;
* ``R`` from the unit quaternion that is the eigenvector of the largest
  eigenvalue of Horn's symmetric 4x4 matrix ``N(M)``, ``M = sum w (p-p̄)(q-q̄)ᵀ``.

A unit quaternion always gives a *proper* rotation (det +1): unlike the plain
SVD (Kabsch) solution, this method never returns a reflection.

Numerical conventions (all documented behaviour, tested in
``tests/blending/test_horn1987.py``):

* Computation is in float64 whatever the input dtype; results are float64.
* Each problem is rescaled (centred, divided by its spread) before ``N`` is
  formed, so tiny (1e-150 m) and huge (1e+150 m) coordinates work.
* **Degenerate sets.**  When either centred set has no spread (all points
  coincident to within ``1e-12`` of the coordinates' magnitude), or the total
  weight is zero, or ``M`` vanishes, every rotation is optimal and the
  **identity** is returned (``t = q̄ - p̄``; ``t = 0`` for zero total weight).
  For collinear sets the rotation about the common line is undetermined; some
  optimal rotation is returned (its residual equals the optimum).
* Non-finite input raises :class:`ValueError` naming the offending shape.
"""
from __future__ import annotations

import numpy as np

__all__ = ["horn", "horn_quaternion", "quaternion_to_matrix", "horn_matrix"]

#: relative spread below which a point set counts as coincident
COINCIDENT_RTOL = 1e-12


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of quaternions ``q`` ``(..., 4)`` ordered ``(w, x, y, z)``.

    ``q`` need not be normalised; it is normalised first (a zero quaternion gives the identity).
    """
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(n > 0, q / np.where(n > 0, n, 1.0), np.array([1.0, 0.0, 0.0, 0.0]))
    w, x, y, z = np.moveaxis(q, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = w * w + x * x - y * y - z * z
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = w * w - x * x + y * y - z * z
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = w * w - x * x - y * y + z * z
    return R


def horn_matrix(M: np.ndarray) -> np.ndarray:
    """Horn's symmetric 4x4 matrix ``N`` ``(..., 4, 4)`` of cross-covariances ``M = Σ p qᵀ`` ``(..., 3, 3)``.

    The quaternion of the optimal rotation (mapping ``p`` onto ``q``) is the eigenvector of
    ``N``'s largest eigenvalue.
    """
    M = np.asarray(M, dtype=np.float64)
    Sxx, Sxy, Sxz = M[..., 0, 0], M[..., 0, 1], M[..., 0, 2]
    Syx, Syy, Syz = M[..., 1, 0], M[..., 1, 1], M[..., 1, 2]
    Szx, Szy, Szz = M[..., 2, 0], M[..., 2, 1], M[..., 2, 2]
    N = np.empty(M.shape[:-2] + (4, 4))
    N[..., 0, 0] = Sxx + Syy + Szz
    N[..., 0, 1] = N[..., 1, 0] = Syz - Szy
    N[..., 0, 2] = N[..., 2, 0] = Szx - Sxz
    N[..., 0, 3] = N[..., 3, 0] = Sxy - Syx
    N[..., 1, 1] = Sxx - Syy - Szz
    N[..., 1, 2] = N[..., 2, 1] = Sxy + Syx
    N[..., 1, 3] = N[..., 3, 1] = Szx + Sxz
    N[..., 2, 2] = -Sxx + Syy - Szz
    N[..., 2, 3] = N[..., 3, 2] = Syz + Szy
    N[..., 3, 3] = -Sxx - Syy + Szz
    return N


def _check(P, Q, weights):
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    if P.ndim < 2 or P.shape[-1] != 3 or P.shape != Q.shape:
        raise ValueError(f"horn: P and Q must both have shape (..., N, 3); got {P.shape} and {Q.shape}")
    if P.shape[-2] == 0:
        raise ValueError(f"horn: need at least one point; got P of shape {P.shape}")
    if not (np.all(np.isfinite(P)) and np.all(np.isfinite(Q))):
        raise ValueError(f"horn: P {P.shape} / Q {Q.shape} contain non-finite values")
    if weights is None:
        w = np.ones(P.shape[:-1])
    else:
        w = np.asarray(weights, dtype=np.float64)
        try:
            w = np.broadcast_to(w, P.shape[:-1])
        except ValueError:
            raise ValueError(f"horn: weights of shape {w.shape} do not broadcast to {P.shape[:-1]}") from None
        if not np.all(np.isfinite(w)) or np.any(w < 0):
            raise ValueError(f"horn: weights {w.shape} must be finite and non-negative")
    return P, Q, w


def horn_quaternion(P, Q, weights=None):
    """Optimal rotation as a unit quaternion: ``(q (..., 4) as (w, x, y, z) with w >= 0, t (..., 3))``.

    See :func:`horn` for the arguments and the degenerate cases.
    """
    P, Q, w = _check(P, Q, weights)
    W = w.sum(axis=-1)                                        # (...)
    Wsafe = np.where(W > 0, W, 1.0)
    wn = w / Wsafe[..., None]
    cp = (wn[..., None, :] @ P)[..., 0, :]
    cq = (wn[..., None, :] @ Q)[..., 0, :]
    Pc = P - cp[..., None, :]
    Qc = Q - cq[..., None, :]
    used = w > 0

    def spread(X):   # max |coordinate| over the used points; the coordinates first (2.4x faster than one max)
        A = np.abs(X)
        return np.where(used, np.maximum(np.maximum(A[..., 0], A[..., 1]), A[..., 2]), 0.0).max(axis=-1)

    sp, sq, mp, mq = spread(Pc), spread(Qc), spread(P), spread(Q)
    degenerate = (W <= 0) | (sp <= COINCIDENT_RTOL * mp) | (sq <= COINCIDENT_RTOL * mq)
    sps = np.where(degenerate, 1.0, sp)
    sqs = np.where(degenerate, 1.0, sq)
    M = np.swapaxes(Pc * (wn / (sps * sqs)[..., None])[..., None], -1, -2) @ Qc
    Mnorm = np.sqrt(np.sum(M * M, axis=(-1, -2)))
    # |M| <= 1 after the rescaling; below ~roundoff every rotation is equally good.
    degenerate |= Mnorm <= 1e-14
    N = horn_matrix(np.where(degenerate[..., None, None], 0.0, M))
    _, vecs = np.linalg.eigh(N)
    q = vecs[..., :, -1]
    q = np.where(q[..., :1] < 0, -q, q)
    q = np.where(degenerate[..., None], np.array([1.0, 0.0, 0.0, 0.0]), q)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    R = quaternion_to_matrix(q)
    t = cq - (R @ cp[..., None])[..., 0]
    t = np.where((W <= 0)[..., None], 0.0, t)
    return q, t


def horn(P, Q, weights=None):
    """Rigid transform ``(R, t)`` minimising ``Σ_i w_i |R p_i + t - q_i|²`` (Horn 1987).

    Parameters
    ----------
    P, Q : array_like, shape ``(..., N, 3)``
        Corresponding points; ``P`` is moved onto ``Q``.  Leading dimensions are batch dimensions.
    weights : array_like, shape ``(..., N)`` (or broadcastable), optional
        Non-negative per-point weights (default: all 1).  Zero-weight points are ignored.

    Returns
    -------
    R : ndarray, shape ``(..., 3, 3)``, float64
        Proper rotation (``det R = +1``, never a reflection).
    t : ndarray, shape ``(..., 3)``, float64
        Translation, ``t = q̄ - R p̄``.

    Degenerate sets (coincident points, zero total weight) give the identity; see the module
    docstring.
    """
    q, t = horn_quaternion(P, Q, weights)
    return quaternion_to_matrix(q), t
