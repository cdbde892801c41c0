"""Numba kernels, imported on first use (:func:`.relight_cpu.kernels`: Numba loads only when a render
needs them): the exact relight sum (:func:`lit_rows`; its layout: :mod:`.relight_cpu`) and the rotated
light basis' trilinear blend of grid nodes (:func:`trilinear_rows`, :meth:`.lighting.RotatedLightBasis.rotated`)."""
import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic


@intrinsic
def _half(typingctx, bits):
    """The float32 value of a float16 given by its 16 bits (uint16): LLVM's ``fpext half to float``, which is
    exact for every half (subnormals, infinities and NaNs included; IEEE 754 widening), the same values as
    :func:`.relight.half_to_float`'s rule. On x86 with F16C and on AArch64 it is one vector instruction
    (``vcvtph2ps``/``fcvtl``) where LLVM vectorises the loop round it; elsewhere a library call."""
    def codegen(context, builder, signature, args):
        return builder.fpext(builder.bitcast(args[0], ir.HalfType()), ir.FloatType())
    return types.float32(types.uint16), codegen


@numba.njit(cache=True, boundscheck=False, nogil=True)
def halves(bits, out):
    """``out[i]`` = the float32 value of the half whose bits are ``bits[i]`` (uint16), by :func:`_half`, the
    decode :func:`lit_rows` uses (tests/rendering/test_relight_cpu.py checks it on all 65,536 halves)."""
    for i in range(bits.shape[0]):
        out[i] = _half(bits[i])


@numba.njit(cache=True, boundscheck=False, nogil=True)
def lit_rows(field, light, ids, bary, fv, lin, cov, weights, images, offset, start, end):
    """Rows ``start``…``end`` of one chunk's lit image (:func:`.relight_cpu.lit_images`): those texels of
    ``field`` (rows, L·3) uint16 whose weight Σ_k b_k a_{v_k} is positive are lit and written, RGB and
    coverage, to ``images`` (4 floats a pixel) from pixel ``offset`` on; returns how many. ``bary`` (rows,
    3) float32, ``fv`` (rows, 3) int64, ``lin`` (rows,) pixel, ``cov`` (rows,) float32 the field's texel
    map; ``weights`` (T,) float64 the chunk's vertex weights; ``light`` (V, K·3) float32 the lighting of
    the lights ``ids`` (K,), all L lights when ``ids`` is empty. Serial and without the GIL: threads run
    calls on disjoint rows at once (a field's texels are distinct pixels, so they write disjoint values)."""
    J = field.shape[1]
    K = ids.shape[0]
    subset = K > 0
    acc = np.empty(48, np.float32)
    lit = 0
    for t in range(start, end):
        v0 = fv[t, 0]
        v1 = fv[t, 1]
        v2 = fv[t, 2]
        w0 = np.float64(bary[t, 0]) * weights[v0]
        w1 = np.float64(bary[t, 1]) * weights[v1]
        w2 = np.float64(bary[t, 2]) * weights[v2]
        ws = w0 + w1 + w2
        if not ws > 0.0:
            continue
        lit += 1
        c0 = np.float32(w0 / ws)
        c1 = np.float32(w1 / ws)
        c2 = np.float32(w2 / ws)
        row = field[t]           # halves, decoded where they are read (_half: exact, one instruction a vector)
        L0 = light[v0]
        L1 = light[v1]
        L2 = light[v2]
        r = np.float32(0)
        g = np.float32(0)
        bb = np.float32(0)
        if subset:
            for k in range(K):
                o = ids[k] * 3
                q = 3 * k
                r += _half(row[o]) * (c0 * L0[q] + c1 * L1[q] + c2 * L2[q])
                g += _half(row[o + 1]) * (c0 * L0[q + 1] + c1 * L1[q + 1] + c2 * L2[q + 1])
                bb += _half(row[o + 2]) * (c0 * L0[q + 2] + c1 * L1[q + 2] + c2 * L2[q + 2])
        else:
            for k in range(48):
                acc[k] = 0.0
            for b in range(J // 48):     # 48 independent sums: 3 channels x 16 lanes
                for k in range(48):
                    j = b * 48 + k
                    acc[k] += _half(row[j]) * (c0 * L0[j] + c1 * L1[j] + c2 * L2[j])
            for k in range(16):
                r += acc[3 * k]
                g += acc[3 * k + 1]
                bb += acc[3 * k + 2]
            for j in range(J - J % 48, J, 3):     # L not a multiple of 16: the rest
                r += _half(row[j]) * (c0 * L0[j] + c1 * L1[j] + c2 * L2[j])
                g += _half(row[j + 1]) * (c0 * L0[j + 1] + c1 * L1[j + 1] + c2 * L2[j + 1])
                bb += _half(row[j + 2]) * (c0 * L0[j + 2] + c1 * L1[j + 2] + c2 * L2[j + 2])
        p = (offset + lin[t]) * 4
        images[p] = r
        images[p + 1] = g
        images[p + 2] = bb
        images[p + 3] = cov[t]
    return lit


@numba.njit(cache=True, boundscheck=False, nogil=True)
def trilinear_rows(values, rows, weights, out):
    """``out[p] = Σ_c weights[c, p] · values[rows[c, p]]`` over the 8 corners c in order, each product
    added to a sum that starts at 0 — the same float64 operations, in the same order, as the NumPy loop of
    :meth:`.lighting.RotatedLightBasis.rotated` (so the same values bit for bit), without its (P, L, 3)
    temporaries. ``values`` (N, L, 3) float64, ``rows`` (8, P) int64, ``weights`` (8, P) float64, ``out``
    (P, L, 3) float64."""
    P = rows.shape[1]
    L = values.shape[1]
    for p in range(P):
        for j in range(L):
            for k in range(3):
                out[p, j, k] = 0.0
        for c in range(8):
            w = weights[c, p]
            r = rows[c, p]
            for j in range(L):
                for k in range(3):
                    out[p, j, k] += values[r, j, k] * w
