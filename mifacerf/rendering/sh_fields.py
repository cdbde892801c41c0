"""Reflectance fields in spherical harmonics, lit in the SH domain (compression method ``sh``).

The paper's own suggestion for compressing reflectance functions (§8). A texel's reflectance function
``F(x)`` (L, 3) is the piecewise-constant function on the sphere that the exact path integrates: F_l
on light l's spherical-Voronoi cell (:mod:`.lighting`: ``Σ_l L_l(R) F_l = ∫ E(Rᵀω) F(ω) dω``). Its SH
coefficients up to band ``order`` (J = (order+1)² per colour)::

    a(x)[j, c] = Σ_l F(x)[l, c] M[l, j],       M[l, j] = ∫_{cell l} Y_j(ω) dω

(:func:`cell_integrals`, a fine quadrature; nested: the coefficients of a lower order are the first
rows). Lighting: the environment's coefficients ``e[j, c] = ∫ E(ω) Y_j(ω) dω`` once, rotated per
(vertex, source) by the local rotation ``R_ts`` **in the SH domain** — ``e(R) = D(R) e`` band by band
(:func:`.ivanic1996.sh_rotation`), no re-integration of the environment. A texel's lit colour is
``Σ_k ĉ_k Σ_j a(x)[j] e_{v_k}(R)[j]`` — the exact path's kernel (:func:`.relight.lit_texels`) with J
terms instead of L. As the order grows it tends to the exact path with the rotation exact (no grid).

Storage: ``fields/<expr>/<cam>.sh<order>.npz`` with ``coeff`` (N, J, 3) float16 (the order is the
knob; sizes and errors: ``mifacerf bench``, docs/rendering.md). Units: those of the fields (linear sRGB
radiance per unit irradiance) times steradians.
"""
from __future__ import annotations

import numpy as np

from ..environment import light_shares, sphere_quadrature
from .ivanic1996 import n_coefficients, real_sh, rotate_coefficients

#: rows of the lat-long quadrature of the cell integrals and of the environment's projection
N_THETA = 256


def cell_integrals(directions: np.ndarray, order: int, n_theta: int = N_THETA) -> np.ndarray:
    """``M`` (L, J): ∫ Y_j over each light's spherical-Voronoi cell (lights ``directions`` (L, 3)); the last
    few are kept (a model's fields share one light stage)."""
    directions = np.ascontiguousarray(directions, np.float64)
    key = (directions.tobytes(), int(order), int(n_theta))
    if key not in _CELL_INTEGRALS:
        if len(_CELL_INTEGRALS) >= 4:
            _CELL_INTEGRALS.pop(next(iter(_CELL_INTEGRALS)))
        _CELL_INTEGRALS[key] = _cell_integrals(directions, int(order), int(n_theta))
    return _CELL_INTEGRALS[key]


_CELL_INTEGRALS: dict = {}


def _cell_integrals(directions: np.ndarray, order: int, n_theta: int) -> np.ndarray:
    qd, qw = sphere_quadrature(n_theta)
    lights, shares = light_shares(qd, directions, "voronoi")
    M = np.zeros((len(directions), n_coefficients(order)))
    step = 1 << 16
    for s in range(0, len(qd), step):
        Y = real_sh(qd[s:s + step], order) * qw[s:s + step, None]
        for k in range(lights.shape[1]):
            np.add.at(M, lights[s:s + step, k], Y * shares[s:s + step, k, None])
    return M


def compress_sh(rf: np.ndarray, orders, directions: np.ndarray) -> dict:
    """SH coefficients of one field: rf (N, L, 3) → {order: {"coeff": (N, (order+1)², 3) float16}}."""
    orders = [int(o) for o in orders]
    top = max(orders)
    M = cell_integrals(directions, top)
    rf = np.asarray(rf)
    coeff = np.empty((len(rf), n_coefficients(top), 3), np.float32)
    step = 1 << 14
    for s in range(0, len(rf), step):
        block = np.asarray(rf[s:s + step], np.float32).transpose(0, 2, 1)          # (n, 3, L)
        coeff[s:s + step] = (block @ M.astype(np.float32)).transpose(0, 2, 1)      # (n, J, 3)
    if np.abs(coeff).max(initial=0.0) > 65000:
        raise ValueError("SH coefficients overflow float16")
    return {o: {"coeff": coeff[:, :n_coefficients(o)].astype(np.float16)} for o in orders}


def reconstruct_sh(coeff: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(N, L, 3) reflectance functions back from SH coefficients (N, J, 3): each light's cell average of the
    expansion, ``F_l = Σ_j a_j M[l, j] / Ω_l`` (Ω_l = the cell's solid angle)."""
    coeff = np.asarray(coeff, np.float32)
    order = int(round(np.sqrt(coeff.shape[1]))) - 1
    M = cell_integrals(directions, order)
    omega = M[:, 0] * np.sqrt(4 * np.pi)            # ∫_cell 1 = √(4π) ∫_cell Y_00
    return (coeff.transpose(0, 2, 1) @ (M / omega[:, None]).T.astype(np.float32)).transpose(0, 2, 1)


def environment_coefficients(env, order: int, n_theta: int = N_THETA) -> np.ndarray:
    """``e`` (J, 3): the environment's SH coefficients ∫ E(ω) Y_j(ω) dω (world directions)."""
    qd, qw = sphere_quadrature(n_theta)
    radiance = env.lookup(qd).astype(np.float64) * qw[:, None]
    out = np.zeros((n_coefficients(order), 3))
    step = 1 << 16
    for s in range(0, len(qd), step):
        out += real_sh(qd[s:s + step], order).T @ radiance[s:s + step]
    return out


# ------------------------------------------------------------------ the method's hooks
def load_sh(model, s: int, c: int, order: int, lights):
    from .relight import to_device_words

    return to_device_words(model.compressed_field(s, c, order, "sh")["coeff"])


def lit_sh(data, n_terms: int, texels, vertex_ids, coef, lighting, keep):
    from .relight import lit_texels

    return lit_texels(data, lighting.shape[1], texels, vertex_ids, coef, lighting, later=True)


def lighting_sh(renderer, env, rotations: np.ndarray) -> np.ndarray:
    """Per-rotation lighting (P, J, 3): the environment's coefficients rotated by each R (P, 3, 3)."""
    order = int(renderer.rank)
    key = ("sh", id(env), order)
    cache = renderer.method_cache
    if key not in cache or cache[key][0] is not env:
        cache[key] = (env, environment_coefficients(env, order))
    return rotate_coefficients(cache[key][1], rotations, order)
