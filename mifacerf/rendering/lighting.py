"""Lighting in the light stage's basis, rotated per vertex and source expression (paper §6.1, Fig. 6).

A reflectance field measured in source expression ``s`` answers "light from world
direction ω_l in the source's pose". When vertex ``i`` of the target has the local
rotation ``R = R_ts`` (target pose → source pose), light reaching it from world
direction ω arrives, in the source's frame, from ``R ω``. The light-stage weights
that relight the source data for that vertex are therefore those of the
environment rotated by R::

    L_l(R) = ∫_{cell l} E(Rᵀ ω) dω          (cell l: light l's spherical-Voronoi cell)

(the default light basis rule, ``voronoi``; ``method="hat"`` weights ω by light l's Delaunay
hat instead, :data:`mifacerf.environment.LIGHT_BASIS_METHODS`).

:class:`RotatedLightBasis` evaluates this for many rotations at once with a
coarse quadrature of the sphere (a lat-long grid with exact solid angles, each
sample in its nearest light's cell) on a pre-filtered copy of the environment
(Gaussian blur of about the quadrature's spacing, so the sparse samples do not
alias), anchored at the exact unrotated basis::

    L(R) = max(0, L_exact(I) + Q(R) − Q(I))

where ``L_exact`` is :func:`mifacerf.environment.light_basis` (fine quadrature)
and ``Q`` the coarse one. So ``R = I`` (a captured expression rendered as itself)
is exact, the result is continuous in R (no jump near the identity, no temporal
scintillation), and the coarse quadrature only has to get the *change* due to the
rotation right. Energy: Σ_l L_l(R) = ∫ E dω for every R, up to the clamp.

Speed: per-frame rotations are mostly small and cluster, so
:meth:`RotatedLightBasis.rotated` interpolates (trilinearly in rotation-vector
space) ``L(R)`` between the nodes of a grid of rotation vectors (spacing
``grid_step_deg``, up to ``grid_radius_deg``); a node is evaluated the first time a
rotation needs it and kept, so an animation pays only for the nodes it visits.
Rotations beyond the grid are evaluated directly. Trilinear interpolation is
continuous across cells, so animated rotations never jump.
"""
from __future__ import annotations

import numpy as np

from ..jitarrays import to_jit
from ..environment import DEFAULT_LIGHT_BASIS_METHOD, Environment, light_basis, light_shares, sphere_quadrature
from ..variant import ensure_variant


def _trilinear_kernel():
    """:func:`._numba_kernels.trilinear_rows` where Numba serves (:func:`.relight_cpu.kernels`), else None
    (the NumPy loop, the same values)."""
    from .relight_cpu import kernels

    k = kernels()
    return None if k is None else k["trilinear"]


def prefilter(env: Environment, sigma_rad: float) -> np.ndarray:
    """Blur a lat-long map by about ``sigma_rad`` on the sphere (wider in u towards the poles).

    Rows are blurred horizontally with a width of ``sigma / sin θ`` (capped), then
    vertically; u wraps, v clamps. Returns (H, W, 3) float32.
    """
    import cv2

    data = env.data.astype(np.float32)
    h, w = data.shape[:2]
    sig_v = sigma_rad / (np.pi / h)
    if sig_v < 0.3:
        return data
    theta = (np.arange(h) + 0.5) / h * np.pi
    out = np.empty_like(data)
    pad = w // 2
    wrapped = np.concatenate([data[:, -pad:], data, data[:, :pad]], axis=1)
    for r in range(h):
        sig_u = min(sig_v / max(np.sin(theta[r]), 1e-3), w / 6)
        k = int(np.ceil(3 * sig_u))
        xs = np.arange(-k, k + 1)
        g = np.exp(-0.5 * (xs / sig_u) ** 2)
        g /= g.sum()
        row = wrapped[r]
        out[r] = sum(g[j] * row[pad + xs[j]: pad + xs[j] + w] for j in range(len(xs)))
    k = int(np.ceil(3 * sig_v))
    out = cv2.GaussianBlur(out, (1, 2 * k + 1), sigmaX=0.1, sigmaY=sig_v, borderType=cv2.BORDER_REPLICATE)
    return out


class RotatedLightBasis:
    """Light-stage weights of one environment under many rotations.

    ``directions`` (L, 3): light directions (world). ``n_theta``: rows of the
    quadrature grid (``2 n_theta`` columns). ``method``: the light basis rule
    (:data:`mifacerf.environment.LIGHT_BASIS_METHODS`; default ``voronoi``, the cells above), used by
    the coarse quadrature and the exact identity alike.
    """

    def __init__(self, env: Environment, directions: np.ndarray, n_theta: int = 96,
                 grid_step_deg: float = 3.0, grid_radius_deg: float = 45.0,
                 method: str = DEFAULT_LIGHT_BASIS_METHOD):
        import drjit as dr

        mi = ensure_variant()
        self.env = env
        self.method = method
        self.directions = np.asarray(directions, np.float64)
        self.n_lights = len(self.directions)
        qd, qw = sphere_quadrature(n_theta)
        lights, shares = light_shares(qd, self.directions, method)
        # one quadrature entry per (sample, light it shares in), grouped by light
        k = lights.shape[1]
        cell = lights.reshape(-1)
        order = np.argsort(cell, kind="stable")
        self.q_dirs = np.repeat(qd, k, axis=0)[order]
        self.q_weights = (np.repeat(qw, k) * shares.reshape(-1))[order]
        self.q_cell = cell[order]
        self.cell_start = np.searchsorted(self.q_cell, np.arange(self.n_lights))
        empty = np.setdiff1d(np.arange(self.n_lights), self.q_cell)
        if len(empty):
            # a light whose cell holds no quadrature sample gets its own direction as one sample
            self.q_dirs = np.concatenate([self.q_dirs, self.directions[empty]])
            self.q_weights = np.concatenate([self.q_weights, np.full(len(empty), 1e-12)])
            self.q_cell = np.concatenate([self.q_cell, empty])
            order = np.argsort(self.q_cell, kind="stable")
            self.q_dirs, self.q_weights, self.q_cell = self.q_dirs[order], self.q_weights[order], self.q_cell[order]
            self.cell_start = np.searchsorted(self.q_cell, np.arange(self.n_lights))
        self.filtered = prefilter(env, sigma_rad=0.5 * np.pi / n_theta)
        h, w = self.filtered.shape[:2]
        self._h, self._w = h, w
        self._tex = to_jit(mi.Float, self.filtered.reshape(-1))
        self._q = to_jit(mi.Vector3f, self.q_dirs.T)
        self._dr = dr
        self._mi = mi
        self.identity = light_basis(env, self.directions, n_theta=max(256, 4 * n_theta), method=method)
        self._q_identity = self._evaluate(np.eye(3)[None])[0]
        self.grid_step = np.radians(grid_step_deg)
        self.grid_n = int(round(grid_radius_deg / grid_step_deg))
        self._nodes: dict[int, int] = {}
        self._node_values = np.zeros((0, self.n_lights, 3))

    def _exact(self, R: np.ndarray) -> np.ndarray:
        """L(R) for rotations (P, 3, 3) by direct quadrature (anchored at the exact identity)."""
        if len(R) == 0:
            return np.zeros((0, self.n_lights, 3))
        delta = self._evaluate(R) - self._q_identity
        return np.maximum(self.identity + delta, 0.0)

    def _node_rows(self, ijk: np.ndarray) -> np.ndarray:
        """Rows of ``_node_values`` for grid nodes (N, 3) (integer offsets from the centre), evaluating new ones."""
        from scipy.spatial.transform import Rotation

        n = 2 * self.grid_n + 1
        keys = ((ijk[:, 0] + self.grid_n) * n + (ijk[:, 1] + self.grid_n)) * n + (ijk[:, 2] + self.grid_n)
        uniq = np.unique(keys)
        new = np.array([k for k in uniq if k not in self._nodes], np.int64)
        if len(new):
            c = np.stack([new // (n * n), (new // n) % n, new % n], axis=1) - self.grid_n
            vals = self._exact(Rotation.from_rotvec(c * self.grid_step).as_matrix())
            vals[np.all(c == 0, axis=1)] = self.identity
            base = len(self._node_values)
            self._node_values = np.concatenate([self._node_values, vals])
            for i, k in enumerate(new):
                self._nodes[int(k)] = base + i
        lut = {k: self._nodes[int(k)] for k in uniq}
        return np.array([lut[k] for k in keys], np.int64)

    def _lookup(self, d):
        """Bilinear lat-long lookup (Dr.Jit) of the pre-filtered map in world directions d."""
        dr, mi = self._dr, self._mi
        h, w = self._h, self._w
        u = dr.atan2(d.x, -d.z) * (1.0 / (2 * np.pi))
        u = u - dr.floor(u)
        v = dr.safe_acos(d.y) * (1.0 / np.pi)
        x = u * w - 0.5
        y = v * h - 0.5
        x0 = dr.floor(x)
        y0 = dr.floor(y)
        fx, fy = x - x0, y - y0
        xi0 = mi.Int32(x0)
        yi0 = mi.Int32(y0)
        xi0 = dr.select(xi0 < 0, xi0 + w, xi0)
        xi1 = dr.select(xi0 + 1 >= w, xi0 + 1 - w, xi0 + 1)
        yi0c = dr.clip(yi0, 0, h - 1)
        yi1c = dr.clip(yi0 + 1, 0, h - 1)
        out = []
        for c in range(3):
            def g(yy, xx):
                return dr.gather(mi.Float, self._tex, mi.UInt32((yy * w + xx) * 3 + c))
            out.append((1 - fy) * ((1 - fx) * g(yi0c, xi0) + fx * g(yi0c, xi1))
                       + fy * ((1 - fx) * g(yi1c, xi0) + fx * g(yi1c, xi1)))
        return out

    def rotated(self, rotations: np.ndarray, identity_tol: float = 1e-9) -> np.ndarray:
        """Weights (P, L, 3) for rotations (P, 3, 3): ``L_l(R) = ∫_{cell l} E(Rᵀ ω) dω``.

        Rotations within ``identity_tol`` (Frobenius) of the identity get the exact
        unrotated weights without evaluating the quadrature.
        """
        from scipy.spatial.transform import Rotation

        R = np.asarray(rotations, np.float64).reshape(-1, 3, 3)
        out = np.empty((len(R), self.n_lights, 3))
        ident = np.linalg.norm(R - np.eye(3), axis=(1, 2)) < identity_tol
        out[ident] = self.identity
        rest = np.flatnonzero(~ident)
        if len(rest) == 0:
            return out
        rv = Rotation.from_matrix(R[rest]).as_rotvec() / self.grid_step
        in_grid = np.all(np.abs(rv) <= self.grid_n - 1e-9, axis=1)
        if (~in_grid).any():
            out[rest[~in_grid]] = self._exact(R[rest[~in_grid]])
        if in_grid.any():
            x = rv[in_grid]
            i0 = np.minimum(np.floor(x).astype(np.int64), self.grid_n - 1)
            f = x - i0
            acc = np.zeros((len(x), self.n_lights, 3))
            corners = [np.array([(c >> 2) & 1, (c >> 1) & 1, c & 1]) for c in range(8)]
            rows = self._node_rows(np.concatenate([i0 + o for o in corners]))
            rows = rows.reshape(8, len(x))
            wgts = np.stack([np.prod(np.where(o, f, 1 - f), axis=1) for o in corners])
            kern = _trilinear_kernel()
            if kern is not None:   # the same sums (float64, in the same order), 4-5x faster
                kern(self._node_values, np.ascontiguousarray(rows, np.int64), wgts, acc)
            else:
                term = np.empty_like(acc)     # one buffer for every corner's term (no temporaries)
                for c in range(8):
                    np.take(self._node_values, rows[c], axis=0, out=term)
                    term *= wgts[c][:, None, None]
                    acc += term
            out[rest[in_grid]] = acc
        return out

    def _evaluate(self, R: np.ndarray) -> np.ndarray:
        dr, mi = self._dr, self._mi
        out = np.empty((len(R), self.n_lights, 3))
        todo = np.arange(len(R))
        nq = len(self.q_dirs)
        chunk = max(1, (1 << 22) // nq)
        for s in range(0, len(todo), chunk):
            sel = todo[s:s + chunk]
            k = len(sel)
            Rt = R[sel].astype(np.float32)  # Rᵀ ω = ω @ R per row
            lane = dr.arange(mi.UInt32, k * nq)
            ri = lane // nq
            qi = lane - ri * nq
            qx = dr.gather(mi.Float, self._q.x, qi)
            qy = dr.gather(mi.Float, self._q.y, qi)
            qz = dr.gather(mi.Float, self._q.z, qi)
            m = [dr.gather(mi.Float, to_jit(mi.Float, Rt[:, a, b]), ri) for a in range(3) for b in range(3)]
            # (Rᵀ q)_b = Σ_a R_ab q_a
            d = mi.Vector3f(m[0] * qx + m[3] * qy + m[6] * qz,
                            m[1] * qx + m[4] * qy + m[7] * qz,
                            m[2] * qx + m[5] * qy + m[8] * qz)
            rgb = self._lookup(d)
            dr.eval(*rgb)    # one kernel for the three channels
            vals = np.stack([np.asarray(c) for c in rgb], axis=-1).reshape(k, nq, 3).astype(np.float64)
            vals *= self.q_weights[None, :, None]
            out[sel] = np.add.reduceat(vals, self.cell_start, axis=1)
        return out
