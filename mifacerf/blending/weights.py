"""Dr.Jit evaluator of blend weights for all (frame × fiducial vertex) pairs at once.

One kernel per dimensionality ``m ∈ {1, 2, 3}`` (``m = 0`` vertices have constant
weights and need none) does, for every lane = (fiducial vertex ``f``, frame ``t``):

1. gather the target's neighbourhood ``P_t(V_f)``;
2. Horn (1987) alignment onto the neutral's neighbourhood: the 4x4 matrix
   ``N(M)`` is diagonalised by cyclic Jacobi sweeps (branch-free, a fixed
   number of sweeps; 5 suffice for float64 on 4x4, 6 are used), the quaternion
   of the largest eigenvalue gives ``R``;
3. projection of the aligned deformation onto the vertex's PCA basis, ``z ∈ R^m``;
4. point location by a **visibility walk** in the vertex's triangulation
   (``dr.while_loop``; start simplex = the one containing the sources'
   centroid; step across the facet of the most negative barycentric).  The walk
   terminates in Delaunay and regular triangulations (Edelsbrunner's
   acyclicity); lanes still walking after ``max_iter`` steps (numerical cycles)
   fall back to a brute-force search over the vertex's simplices.  A walk that
   ends in a ghost sliver (:mod:`.delaunay`, rule 4b) counts as outside;
5. barycentric weights in closed form (``T (z - r)``), or — when the walk leaves
   the hull through a boundary facet — the barycentrics of the nearest point on
   the hull (a loop over the vertex's hull facets: point, segment or triangle
   closest-point tests; in float64 in both precisions, see below).

``precision`` (``float32`` or ``float64``, both tested) applies to steps 1–3,
the bulk of the work.  Location (steps 4–5) always runs in float64 on the
(rounded) coordinates: thin simplices have barycentric transforms of 1e3–1e6,
and float32 arithmetic there made walks leave the hull from deep inside it
(weights off by up to 1; caught by the float32/float64 test on out-of-set
targets of the synthetic subject).  The float32 path's remaining error is the
rounding of the coordinates times the weights' Lipschitz constant.  Scalars that may change between calls (tolerances, sizes) are passed
as opaque arrays so the kernels are compiled once.  Index arrays are
bound-checked in NumPy before they are handed to ``dr.gather``, which does not
check them (32-bit indices).

The NumPy reference in :mod:`mifacerf.blending.reference` computes the same
weights in the straightforward way.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.ericson2004 import region_barycentrics

__all__ = ["backend", "GroupTables", "evaluate_group", "horn_rotations", "JACOBI_SWEEPS"]

#: Jacobi sweeps for the 4x4 eigenproblem of Horn's method
JACOBI_SWEEPS = {"float32": 5, "float64": 6}
#: at most this many lanes per kernel launch
MAX_LANES = 1 << 22


def backend():
    """The Dr.Jit array namespace for mifacerf's variant (``drjit.llvm`` or ``drjit.cuda``), or None.

    The variant is chosen only through :func:`mifacerf.variant.ensure_variant`; scalar variants have no
    vectorised backend (callers then fall back to the NumPy reference).
    """
    from mifacerf.variant import ensure_variant

    mi = ensure_variant()
    name = mi.variant()
    if name.startswith("cuda"):
        import drjit.cuda as B
    elif name.startswith("llvm"):
        import drjit.llvm as B
    else:
        return None
    return B


@dataclass
class GroupTables:
    """Flat tables of the fiducials of one dimensionality ``m`` (built by ``BlendModel``).

    Shapes (``G`` fiducials in the group, ``K`` neighbourhood width, ``S``/``H`` simplices/facets of the
    whole group; all indices already global within the group):

    nb_idx ``(G, K)`` int   template vertex ids; nb_w ``(G, K)`` 0/1 weights
    ref ``(G, K, 3)``      neutral neighbourhood centred on its (weighted) centroid
    basis ``(G, m, K, 3)`` PCA directions divided by the PCA scale (zero on padding)
    z0 ``(G, m)``          the neutral's own coordinates ``<P_0(V) - mean, basis>``
    T ``(S, m, m)``, r ``(S, m)``, nbr ``(S, m+1)`` (-1 = boundary), sid ``(S, m+1)`` source ids,
    ghost ``(S,)`` 1 for ghost slivers (a target inside one counts as outside)
    s_start ``(G,)``, s_first ``(G,)``, s_count ``(G,)``   walk start; the group's simplex range per vertex
    fpts ``(H, m, m)`` facet vertex coordinates, fsid ``(H, m)`` source ids, f_first/f_count ``(G,)``
    """

    m: int
    nb_idx: np.ndarray
    nb_w: np.ndarray
    ref: np.ndarray
    basis: np.ndarray
    z0: np.ndarray
    T: np.ndarray
    r: np.ndarray
    nbr: np.ndarray
    sid: np.ndarray
    ghost: np.ndarray
    s_start: np.ndarray
    s_first: np.ndarray
    s_count: np.ndarray
    fpts: np.ndarray
    fsid: np.ndarray
    f_first: np.ndarray
    f_count: np.ndarray

    def check(self, n_vertices: int, n_sources: int) -> None:
        """Bound-check every index array (dr.gather does not)."""
        S, H, G = self.T.shape[0], self.fpts.shape[0], self.nb_idx.shape[0]

        def inrange(a, lo, hi, what):
            a = np.asarray(a)
            if a.size and (a.min() < lo or a.max() >= hi):
                raise IndexError(f"blending tables: {what} out of range [{lo}, {hi})")

        inrange(self.nb_idx, 0, n_vertices, "neighbourhood vertex id")
        inrange(self.nbr, -1, S, "simplex neighbour")
        inrange(self.sid, 0, n_sources, "simplex source id")
        inrange(self.fsid, 0, n_sources, "facet source id")
        inrange(self.s_start, 0, S, "start simplex")
        inrange(self.s_first, 0, max(S, 1), "simplex range")
        inrange(self.s_first + self.s_count, 1, S + 1, "simplex range end")
        if H:
            inrange(self.f_first, 0, H, "facet range")
            inrange(self.f_first + self.f_count, 1, H + 1, "facet range end")
        if np.any(self.f_count < 1) or np.any(self.s_count < 1):
            raise IndexError("blending tables: every vertex needs >= 1 simplex and >= 1 hull facet")
        if self.basis.shape[0] != G:
            raise ValueError("blending tables: inconsistent group size")


# ----------------------------------------------------------------------------------------------- kernel
def _jacobi4(A, sweeps, Float):
    """Eigen-decomposition of symmetric 4x4 ``A`` (list of lists of arrays) by cyclic Jacobi."""
    A = [row[:] for row in A]
    one, zero = Float(1.0), Float(0.0)
    V = [[one if r == c else zero for c in range(4)] for r in range(4)]
    import drjit as dr

    for _ in range(sweeps):
        for p in range(3):
            for q in range(p + 1, 4):
                apq, app, aqq = A[p][q], A[p][p], A[q][q]
                nz = apq != 0
                theta = (aqq - app) / dr.select(nz, 2 * apq, 1.0)
                t = dr.sign(theta) / (dr.abs(theta) + dr.sqrt(dr.fma(theta, theta, 1.0)))
                t = dr.select(nz, t, 0.0)
                c = dr.rsqrt(dr.fma(t, t, 1.0))
                s = t * c
                A[p][p] = app - t * apq
                A[q][q] = aqq + t * apq
                A[p][q] = A[q][p] = zero
                for r in range(4):
                    if r != p and r != q:
                        arp, arq = A[r][p], A[r][q]
                        A[r][p] = A[p][r] = c * arp - s * arq
                        A[r][q] = A[q][r] = s * arp + c * arq
                for r in range(4):
                    vrp, vrq = V[r][p], V[r][q]
                    V[r][p] = c * vrp - s * vrq
                    V[r][q] = s * vrp + c * vrq
    return [A[i][i] for i in range(4)], V


def _horn_rotation(M, sweeps, Float):
    """Rotation (3x3 list) maximising ``tr(Rᵀ M)`` for ``M = Σ p qᵀ`` (3x3 list), via Horn's quaternion."""
    import drjit as dr

    norm = dr.sqrt(sum(M[a][b] * M[a][b] for a in range(3) for b in range(3)))
    inv = dr.select(norm > 0, dr.rcp(dr.select(norm > 0, norm, 1.0)), 0.0)
    (Sxx, Sxy, Sxz), (Syx, Syy, Syz), (Szx, Szy, Szz) = [[M[a][b] * inv for b in range(3)] for a in range(3)]
    N = [[Sxx + Syy + Szz, Syz - Szy, Szx - Sxz, Sxy - Syx],
         [Syz - Szy, Sxx - Syy - Szz, Sxy + Syx, Szx + Sxz],
         [Szx - Sxz, Sxy + Syx, -Sxx + Syy - Szz, Syz + Szy],
         [Sxy - Syx, Szx + Sxz, Syz + Szy, -Sxx - Syy + Szz]]
    lam, V = _jacobi4(N, sweeps, Float)
    best, q = lam[0], [V[r][0] for r in range(4)]
    for c in range(1, 4):
        better = lam[c] > best
        best = dr.select(better, lam[c], best)
        q = [dr.select(better, V[r][c], q[r]) for r in range(4)]
    w, x, y, z = q
    n2 = w * w + x * x + y * y + z * z
    s2 = 2.0 / n2
    return [[1.0 - s2 * (y * y + z * z), s2 * (x * y - w * z), s2 * (x * z + w * y)],
            [s2 * (x * y + w * z), 1.0 - s2 * (x * x + z * z), s2 * (y * z - w * x)],
            [s2 * (x * z - w * y), s2 * (y * z + w * x), 1.0 - s2 * (x * x + y * y)]]


def _closest_triangle(p, a, b, c, dr):
    """Ericson's closest point on a triangle, branch-free; returns barycentrics (u, v, w)."""
    dot = lambda x, y: x[0] * y[0] + x[1] * y[1] + x[2] * y[2]
    sub = lambda x, y: [x[i] - y[i] for i in range(3)]
    ab, ac, ap, bp, cp = sub(b, a), sub(c, a), sub(p, a), sub(p, b), sub(p, c)
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    return region_barycentrics(d1, d2, d3, d4, d5, d6, dr.select)


def _types(B, precision):
    if precision == "float32":
        return B.Float, np.float32
    if precision == "float64":
        return B.Float64, np.float64
    raise ValueError(f"precision must be 'float32' or 'float64'; got {precision!r}")


def evaluate_group(g: GroupTables, targets_vt: np.ndarray, precision: str = "float32",
                   inside_tol: float | None = None, max_iter: int | None = None, B=None,
                   return_coords: bool = False):
    """Weights of one dimensionality group for all frames.

    Parameters
    ----------
    g : GroupTables (already bound-checked)
    targets_vt : ndarray ``(V, T, 3)``
        Target meshes **minus the neutral**, vertex-major (one vertex's frames are contiguous).
        Displacements are small numbers, which keeps float32 accurate to ~1e-9 m.
    precision : "float32" | "float64"
    inside_tol : float
        Barycentric tolerance of the inside test (default 1e-10; location runs in float64).
    max_iter : int
        Walk steps before the brute-force fallback (default ``2 * max simplices per vertex + 8``).

    Returns
    -------
    ids : ndarray ``(G, T, m+1)`` int32, w : ndarray ``(G, T, m+1)`` float (the working precision),
    and, with ``return_coords``, the projected coordinates ``(G, T, m)``.
    """
    import drjit as dr

    B = B or backend()
    Float, npf = _types(B, precision)
    Int, UInt, Bool = B.Int, B.UInt, B.Bool
    m = g.m
    G, K = g.nb_idx.shape
    V, T = targets_vt.shape[:2]
    if inside_tol is None:
        inside_tol = 1e-10
    if max_iter is None:
        max_iter = 2 * int(g.s_count.max()) + 8
    sweeps = JACOBI_SWEEPS[precision]

    # ---- tables → device (once per call), through 64-byte-aligned copies: Dr.Jit records a mapped
    #      array's alignment in the kernel, so varying NumPy alignments would recompile it
    from mifacerf.jitarrays import to_jit

    F_ = lambda a: to_jit(Float, np.ascontiguousarray(a, dtype=npf).ravel())
    I_ = lambda a: to_jit(Int, np.ascontiguousarray(a, dtype=np.int32).ravel())
    tgt = F_(targets_vt)
    nb_idx = to_jit(UInt, np.ascontiguousarray(g.nb_idx, dtype=np.uint32).ravel())
    nb_w, ref, basis, z0 = (F_(a) for a in (g.nb_w, g.ref, g.basis, g.z0))
    F64 = B.Float64
    D_ = lambda a: to_jit(F64, np.ascontiguousarray(a, dtype=np.float64).ravel())
    Tt, rr, fpts64 = D_(g.T), D_(g.r), D_(g.fpts)
    nbr, sid, ghost, s_start, s_first, s_count, fsid, f_first, f_count = (
        I_(a) for a in (g.nbr, g.sid, g.ghost, g.s_start, g.s_first, g.s_count, g.fsid, g.f_first, g.f_count))
    eps = dr.opaque(F64, inside_tol)
    big64 = dr.opaque(F64, np.finfo(np.float64).max)
    it_max = dr.opaque(Int, max_iter)
    T_op = dr.opaque(UInt, T)

    if V * T * 3 >= 2 ** 32:
        raise ValueError(f"targets too large for 32-bit gathers: {V} x {T} x 3")
    frames_per_launch = max(1, MAX_LANES // max(G, 1))
    ids_out = np.empty((G, T, m + 1), dtype=np.int32)
    w_out = np.empty((G, T, m + 1), dtype=npf)
    z_out = np.empty((G, T, m), dtype=npf) if return_coords else None

    for t0 in range(0, T, frames_per_launch):
        Tc = min(frames_per_launch, T - t0)
        lane = dr.arange(UInt, G * Tc)
        Tc_op = dr.opaque(UInt, Tc)
        f = lane // Tc_op
        t = lane - f * Tc_op + dr.opaque(UInt, t0)
        fi = Int(f)

        # -------- 1) neighbourhood, centred on its first (centre) vertex.  The targets arrive as
        #          displacements from the neutral (small numbers, so float32 keeps ~1e-9 m); positions
        #          are rebuilt relative to the centre from the neutral's (centred) neighbourhood.
        P, W, Qn = [], [], []
        for j in range(K):
            vid = dr.gather(UInt, nb_idx, f * K + j)
            base = (vid * T_op + t) * 3
            Qn.append([dr.gather(Float, ref, (f * K + j) * 3 + c) for c in range(3)])
            P.append([dr.gather(Float, tgt, base + c) for c in range(3)])
            W.append(dr.gather(Float, nb_w, f * K + j))
        d0, q0 = P[0], Qn[0]
        P = [[(Qn[j][c] - q0[c]) + (P[j][c] - d0[c]) for c in range(3)] for j in range(K)]
        wsum = sum(W)
        cp = [sum(W[j] * P[j][c] for j in range(K)) / wsum for c in range(3)]
        P = [[p[c] - cp[c] for c in range(3)] for p in P]
        # -------- 2) Horn: M = Σ w p qᵀ (q centred), R maps the target onto the neutral
        M = [[Float(0.0) for _ in range(3)] for _ in range(3)]
        for j in range(K):
            for a in range(3):
                wp = W[j] * P[j][a]
                for b in range(3):
                    M[a][b] = dr.fma(wp, Qn[j][b], M[a][b])
        R = _horn_rotation(M, sweeps, Float)
        # -------- 3) projection of the displacement from the neutral (small numbers: no cancellation)
        #          z = <R (p - p̄) - (q - q̄), basis> + z_neutral
        z = [dr.gather(Float, z0, f * m + k) for k in range(m)]
        for j in range(K):
            a = [R[i][0] * P[j][0] + R[i][1] * P[j][1] + R[i][2] * P[j][2] - Qn[j][i] for i in range(3)]
            for k in range(m):
                e = ((f * m + k) * K + j) * 3
                z[k] = dr.fma(a[0], dr.gather(Float, basis, e), z[k])
                z[k] = dr.fma(a[1], dr.gather(Float, basis, e + 1), z[k])
                z[k] = dr.fma(a[2], dr.gather(Float, basis, e + 2), z[k])

        # -------- 4) location, always in float64: thin simplices have huge barycentric transforms, and
        #          float32 arithmetic there sends walks out of the hull from deep inside it.  (The
        #          float32 path's remaining error is z's own rounding times the weights' Lipschitz
        #          constant.)
        zh = [F64(zk) for zk in z]

        def bary(s):
            si = UInt(s)
            rr_ = [zh[k] - dr.gather(F64, rr, si * m + k) for k in range(m)]
            b = []
            for i in range(m):
                acc = F64(0.0)
                for k in range(m):
                    acc = dr.fma(dr.gather(F64, Tt, (si * m + i) * m + k), rr_[k], acc)
                b.append(acc)
            b.append(1.0 - sum(b))
            return b

        # -------- 4) visibility walk
        def w_cond(s, done, outside, it):
            return ~done & (it < it_max)

        def w_body(s, done, outside, it):
            b = bary(s)
            jmin, bmin = Int(0), b[0]
            for j in range(1, m + 1):
                lt = b[j] < bmin
                jmin = dr.select(lt, j, jmin)
                bmin = dr.select(lt, b[j], bmin)
            nb = dr.gather(Int, nbr, UInt(s) * (m + 1) + UInt(jmin))
            inside = bmin >= -eps
            exit_out = ~inside & (nb < 0)
            fin = inside | exit_out
            return dr.select(fin, s, nb), fin, exit_out, it + 1

        s0 = dr.gather(Int, s_start, f)
        s, done, outside, _ = dr.while_loop(
            state=(s0, Bool(False), Bool(False), Int(0)), cond=w_cond, body=w_body, label="blend_walk")

        # fallback: brute force for lanes whose walk did not finish
        stuck = ~done
        first = dr.gather(Int, s_first, f)
        count = dr.gather(Int, s_count, f)

        def b_cond(k, best_s, best_min):
            return stuck & (k < count)

        def b_body(k, best_s, best_min):
            sk = first + k
            b = bary(sk)
            bmin = b[0]
            for j in range(1, m + 1):
                bmin = dr.minimum(bmin, b[j])
            bmin = dr.select(dr.gather(Int, ghost, sk) != 0, -big64, bmin)
            better = bmin > best_min
            return k + 1, dr.select(better, sk, best_s), dr.select(better, bmin, best_min)

        _, best_s, best_min = dr.while_loop(
            state=(Int(0), Int(s), -big64), cond=b_cond, body=b_body, label="blend_bruteforce")
        s = dr.select(stuck, best_s, s)
        outside = dr.select(stuck, best_min < -eps, outside)
        outside |= dr.gather(Int, ghost, s) != 0         # landed in a ghost sliver: nearest-boundary rule

        # -------- 5a) inside: clamped, renormalised barycentrics
        b = bary(s)
        b = [dr.maximum(x, 0.0) for x in b]
        bs = sum(b)
        b = [x / dr.select(bs > 0, bs, 1.0) for x in b]
        ids = [dr.gather(Int, sid, UInt(s) * (m + 1) + j) for j in range(m + 1)]

        # -------- 5b) outside: nearest point on the hull facets (float64 too: far from the hull the
        #          facets' distances differ by tiny relative amounts).
        ffirst = dr.gather(Int, f_first, f)
        fcount = dr.gather(Int, f_count, f)
        def facet_weights(h):
            hu = UInt(h)
            Vt = [[dr.gather(F64, fpts64, (hu * m + i) * m + c) for c in range(m)] for i in range(m)]
            if m == 1:
                d = zh[0] - Vt[0][0]
                return [F64(1.0)], d * d
            if m == 2:
                ab = [Vt[1][c] - Vt[0][c] for c in range(2)]
                den = ab[0] * ab[0] + ab[1] * ab[1]
                num = (zh[0] - Vt[0][0]) * ab[0] + (zh[1] - Vt[0][1]) * ab[1]
                tt = dr.clip(num / dr.select(den > 0, den, 1.0), 0.0, 1.0)
                d = [zh[c] - (Vt[0][c] + tt * ab[c]) for c in range(2)]
                return [1.0 - tt, tt], d[0] * d[0] + d[1] * d[1]
            u, v, w = _closest_triangle(zh, Vt[0], Vt[1], Vt[2], dr)
            d = [zh[c] - (u * Vt[0][c] + v * Vt[1][c] + w * Vt[2][c]) for c in range(3)]
            return [u, v, w], d[0] * d[0] + d[1] * d[1] + d[2] * d[2]

        def h_cond(k, best_h, best_d2):
            return outside & (k < fcount)

        def h_body(k, best_h, best_d2):
            h = ffirst + k
            _, d2 = facet_weights(h)
            better = d2 < best_d2
            return k + 1, dr.select(better, h, best_h), dr.select(better, d2, best_d2)

        _, best_h, _ = dr.while_loop(
            state=(Int(0), Int(ffirst), big64), cond=h_cond, body=h_body, label="blend_hull")
        fb, _ = facet_weights(best_h)
        fb = [dr.maximum(x, 0.0) for x in fb]
        fs = sum(fb)
        fb = [x / dr.select(fs > 0, fs, 1.0) for x in fb]
        fids = [dr.gather(Int, fsid, UInt(best_h) * m + j) for j in range(m)]
        ids = [dr.select(outside, fids[j] if j < m else fids[0], ids[j]) for j in range(m + 1)]
        ws = [Float(dr.select(outside, fb[j] if j < m else F64(0.0), b[j])) for j in range(m + 1)]

        dr.eval(ids, ws, z if return_coords else [])
        sl = slice(t0, t0 + Tc)
        for j in range(m + 1):
            ids_out[:, sl, j] = np.asarray(ids[j].numpy()).reshape(G, Tc)
            w_out[:, sl, j] = np.asarray(ws[j].numpy()).reshape(G, Tc)
        if return_coords:
            for k in range(m):
                z_out[:, sl, k] = np.asarray(z[k].numpy()).reshape(G, Tc)
    if return_coords:
        return ids_out, w_out, z_out
    return ids_out, w_out


def horn_rotations(P, Q, weights=None, precision: str = "float64", B=None) -> np.ndarray:
    """The kernel's Horn rotation on NumPy data (for tests): ``P, Q`` ``(N, k, 3)`` → ``R`` ``(N, 3, 3)``.

    Same conventions as :func:`mifacerf.geometry.horn1987.horn` (``R`` maps ``P`` onto ``Q``); computed by the
    Jacobi-sweep code that runs inside the evaluator.
    """
    import drjit as dr

    B = B or backend()
    Float, npf = _types(B, precision)
    P = np.asarray(P, dtype=np.float64)
    Q = np.asarray(Q, dtype=np.float64)
    N, k = P.shape[:2]
    w = np.ones((N, k)) if weights is None else np.broadcast_to(np.asarray(weights, dtype=np.float64), (N, k))
    W = w.sum(axis=1, keepdims=True)
    P = P - P[:, :1]          # as in the kernel: local origin at the first point (exact for coincident sets)
    Q = Q - Q[:, :1]
    Pc = P - np.einsum("nk,nkc->nc", w, P)[:, None] / W[..., None]
    Qc = Q - np.einsum("nk,nkc->nc", w, Q)[:, None] / W[..., None]
    M = np.einsum("nk,nka,nkb->nab", w, Pc, Qc)
    Md = [[Float(M[:, a, b].astype(npf)) for b in range(3)] for a in range(3)]
    R = _horn_rotation(Md, JACOBI_SWEEPS[precision], Float)
    dr.eval(R)
    return np.stack([np.stack([np.asarray(R[a][b].numpy(), dtype=np.float64) for b in range(3)], -1)
                     for a in range(3)], -2)
