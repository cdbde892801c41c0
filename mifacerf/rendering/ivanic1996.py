"""Real spherical harmonics and their rotation matrices per band (Ivanic & Ruedenberg 1996).

J. Ivanic, K. Ruedenberg, "Rotation matrices for real spherical harmonics. Direct determination by
recursion", J. Phys. Chem. 100 (1996) 6342–6347, with the corrections of J. Phys. Chem. A 102 (1998)
9099–9100: the (2l+1)² rotation matrix of band l is a recursion in the matrices of band l−1 and band 1,
so a rotation of an order-n expansion costs Σ_l (2l+1)² products and no quadrature.

Conventions (world frame, unit directions ω = (x, y, z), θ from +z, φ = atan2(y, x)); coefficient
``j = l² + l + m`` for band l, −l ≤ m ≤ l; no Condon–Shortley phase::

    Y_l^0  = K_l^0 P_l^0(cos θ)
    Y_l^m  = √2 K_l^m cos(m φ) P_l^m(cos θ)        (m > 0)
    Y_l^-m = √2 K_l^m sin(m φ) P_l^m(cos θ)        (m > 0),     K_l^m = √((2l+1)/4π · (l−m)!/(l+m)!)

so band 1 is ``√(3/4π) (y, z, x)``. :func:`sh_rotation` returns, per band, ``D_l(R)`` with
``f(Rᵀ ω) = Σ_lm (D(R) a)_lm Y_lm(ω)`` for ``f(ω) = Σ a_lm Y_lm(ω)``: the coefficients of a function
turned by R (tested against direct projection in ``tests/rendering/test_sh.py``).
"""
from __future__ import annotations

from math import factorial, pi, sqrt

import numpy as np


def n_coefficients(order: int) -> int:
    """(order + 1)²: the coefficients of an expansion up to band ``order``."""
    return (int(order) + 1) ** 2


def real_sh(directions: np.ndarray, order: int) -> np.ndarray:
    """Real spherical harmonics (N, (order+1)²) of unit directions (N, 3), bands 0 … ``order``."""
    d = np.asarray(directions, np.float64).reshape(-1, 3)
    if order < 0:
        raise ValueError(f"SH order must be >= 0, got {order}")
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    ct = np.clip(z, -1.0, 1.0)
    st = np.sqrt(np.maximum(0.0, 1.0 - ct * ct))
    phi = np.arctan2(y, x)
    out = np.zeros((len(d), n_coefficients(order)))
    # associated Legendre P_l^m(cos θ) without the Condon–Shortley phase, by the standard recurrences
    P = {}
    pmm = np.ones_like(ct)
    for m in range(order + 1):
        if m > 0:
            pmm = pmm * (2 * m - 1) * st
        P[(m, m)] = pmm
        if m + 1 <= order:
            P[(m + 1, m)] = ct * (2 * m + 1) * pmm
        for l in range(m + 2, order + 1):
            P[(l, m)] = ((2 * l - 1) * ct * P[(l - 1, m)] - (l + m - 1) * P[(l - 2, m)]) / (l - m)
    for l in range(order + 1):
        for m in range(l + 1):
            k = sqrt((2 * l + 1) / (4 * pi) * factorial(l - m) / factorial(l + m))
            if m == 0:
                out[:, l * l + l] = k * P[(l, 0)]
            else:
                out[:, l * l + l + m] = sqrt(2) * k * np.cos(m * phi) * P[(l, m)]
                out[:, l * l + l - m] = sqrt(2) * k * np.sin(m * phi) * P[(l, m)]
    return out


def sh_rotation(rotations: np.ndarray, order: int) -> list[np.ndarray]:
    """Rotation matrices per band of rotations (P, 3, 3): a list of (P, 2l+1, 2l+1), l = 0 … ``order``
    (Ivanic & Ruedenberg's recursion; index ``m + l``)."""
    R = np.asarray(rotations, np.float64).reshape(-1, 3, 3)
    n = len(R)
    bands = [np.ones((n, 1, 1))]
    if order == 0:
        return bands
    # band 1 in the (y, z, x) order of Y_1^{-1}, Y_1^0, Y_1^1
    perm = [1, 2, 0]
    r1 = R[:, perm][:, :, perm]
    bands.append(r1)
    for l in range(2, order + 1):
        prev = bands[l - 1]

        def c1(i, j):                      # band 1, centred indices
            return r1[:, i + 1, j + 1]

        def cp(a, b):                      # band l-1, centred indices
            return prev[:, a + l - 1, b + l - 1]

        def P(i, a, b):
            if b == l:
                return c1(i, 1) * cp(a, l - 1) - c1(i, -1) * cp(a, -l + 1)
            if b == -l:
                return c1(i, 1) * cp(a, -l + 1) + c1(i, -1) * cp(a, l - 1)
            return c1(i, 0) * cp(a, b)

        band = np.zeros((n, 2 * l + 1, 2 * l + 1))
        for m in range(-l, l + 1):
            for k in range(-l, l + 1):
                d = 1.0 if m == 0 else 0.0
                denom = 2 * l * (2 * l - 1) if abs(k) == l else (l + k) * (l - k)
                u = sqrt((l + m) * (l - m) / denom)
                v = 0.5 * sqrt((1 + d) * (l + abs(m) - 1) * (l + abs(m)) / denom) * (1 - 2 * d)
                w = -0.5 * sqrt((l - abs(m) - 1) * (l - abs(m)) / denom) * (1 - d)
                val = np.zeros(n)
                if u:
                    val = val + u * P(0, m, k)
                if v:
                    if m == 0:
                        V = P(1, 1, k) + P(-1, -1, k)
                    elif m > 0:
                        V = P(1, m - 1, k) * sqrt(1 + (m == 1)) - (P(-1, -m + 1, k) if m != 1 else 0.0)
                    else:
                        V = (P(1, m + 1, k) if m != -1 else 0.0) + P(-1, -m - 1, k) * sqrt(1 + (m == -1))
                    val = val + v * V
                if w:
                    if m > 0:
                        W = P(1, m + 1, k) + P(-1, -m - 1, k)
                    else:
                        W = P(1, m - 1, k) - P(-1, -m + 1, k)
                    val = val + w * W
                band[:, m + l, k + l] = val
        bands.append(band)
    return bands


def rotate_coefficients(coefficients: np.ndarray, rotations: np.ndarray, order: int) -> np.ndarray:
    """Coefficients (J, C) of a function turned by each rotation (P, 3, 3): (P, J, C), J = (order+1)²
    (band by band, ``D_l(R) a_l``)."""
    a = np.asarray(coefficients, np.float64)
    out = np.empty((len(np.asarray(rotations).reshape(-1, 3, 3)), n_coefficients(order), a.shape[1]))
    for l, D in enumerate(sh_rotation(rotations, order)):
        out[:, l * l:(l + 1) ** 2] = np.einsum("pmk,kc->pmc", D, a[l * l:(l + 1) ** 2])
    return out
