"""Dr.Jit kernels of the exact relighting path.

:func:`lit_texels` lights a reflectance field in its own camera's image space (the
paper's Fig. 7, third row): for each texel ``x`` of field (s, c) lying on template
triangle (v0, v1, v2) with barycentrics b, and per-vertex chunk weights a_v::

    T(x) = Σ_k ĉ_k Σ_l L_{v_k}[l] ⊙ F(x)[l],      ĉ_k = b_k a_{v_k} / Σ_j b_j a_{v_j}

where L_v (L, 3) is vertex v's rotated light-stage lighting for source s and
F(x) (L, 3) the texel's reflectance function: a sum over *all* lights, no
approximation. One Dr.Jit wavefront over texels, a symbolic loop over lights.
"""
from __future__ import annotations

import numpy as np

from ..jitarrays import to_jit
from ..variant import ensure_variant


def to_device_f16(array: np.ndarray):
    """A flat Dr.Jit Float16 array of a (…) float16 NumPy array (kept by callers as a cache)."""
    import drjit as dr

    mi = ensure_variant()
    F16 = dr.float16_array_t(mi.Float)
    return to_jit(F16, np.asarray(array).reshape(-1))


class HalfWords:
    """A float16 array on the device as 64-bit words, four halves each (lowest half first), the form
    :func:`lit_texels` reads fastest: one 64-bit gather fetches four halves, decoded exactly by
    :func:`half_to_float` (a Float16 gather is emulated lane by lane on the CPU; the exact relight kernel
    reads its fields 2-3x faster this way, same values bit for bit). ``words`` (UInt64); ``size``: the
    halves held (the last word padded with zeros); ``halves`` the same halves on the host (flat float16,
    the memory-mapped field itself where it could be read in place), which :mod:`.relight_cpu` reads."""

    def __init__(self, array: np.ndarray):
        mi = ensure_variant()
        flat = np.asarray(array, np.float16).reshape(-1)   # a view of a memory-mapped field
        self.size = flat.size
        if flat.size % 4 == 0 and flat.flags.c_contiguous and flat.ctypes.data % 64 == 0:
            # whole words already, 64-byte aligned (a .npy field's data starts at a multiple of 64 in a
            # page-aligned map): Dr.Jit reads them where they are (it maps NumPy memory, no copy), so a
            # field costs no memory of its own beyond the page cache, and no copy; kept referenced here
            self.halves = flat
            self.words = mi.UInt64(flat.view(np.uint64))
            return
        n_words = -(-flat.size // 4)
        # the halves copied once, straight into a 64-byte-aligned buffer of whole words (as jitarrays.to_jit
        # hands Dr.Jit its arrays), not padded, made contiguous and aligned in three copies of the field
        buf = np.empty(n_words * 8 + 64, np.uint8)
        start = (-buf.ctypes.data) % 64
        words = buf[start:start + n_words * 8].view(np.uint64)
        halves = words.view(np.uint16)
        halves[:flat.size] = flat.view(np.uint16)
        halves[flat.size:] = 0
        self.halves = halves[:flat.size].view(np.float16)   # the host copy, read by the CPU kernel
        self.words = mi.UInt64(words)


def to_device_words(array: np.ndarray) -> HalfWords:
    """A float16 NumPy array (…) as :class:`HalfWords` (kept by callers as a cache)."""
    return HalfWords(array)


class DeviceLighting:
    """Per-vertex light-stage weights (V, K, 3) with the device forms :func:`lit_texels` reads, each made on
    first use and kept: a frame's chunks of one source (one per capture camera) share one lighting, which
    was re-laid-out and uploaded for every chunk (1.8 MB each for 801 vertices x 192 lights). ``array``
    the NumPy array (also ``np.asarray(self)``); ``flat`` (Float, V*K*3); ``quads`` (UInt64: the (V, K/4,
    3, 4) layout of the four-lights-at-a-time kernel)."""

    def __init__(self, lighting: np.ndarray):
        self.array = np.asarray(lighting)
        self._flat = self._quads = self._rows = None

    @property
    def shape(self) -> tuple:
        return self.array.shape

    def __array__(self, dtype=None, copy=None):
        return self.array if dtype is None else self.array.astype(dtype)

    @property
    def flat(self):
        if self._flat is None:
            self._flat = to_jit(ensure_variant().Float, self.array.reshape(-1))
        return self._flat

    @property
    def rows(self) -> np.ndarray:
        """(V, K*3) float32, contiguous: the rows :mod:`.relight_cpu` reads."""
        if self._rows is None:
            self._rows = np.ascontiguousarray(np.asarray(self.array, np.float32).reshape(self.array.shape[0], -1))
        return self._rows

    @property
    def quads(self):
        if self._quads is None:
            k = self.array.shape[1]
            quads = np.ascontiguousarray(np.asarray(self.array, np.float32).reshape(-1, k // 4, 4, 3).transpose(0, 1, 3, 2))
            self._quads = to_jit(ensure_variant().UInt64, quads.reshape(-1).view(np.uint64))
        return self._quads


def half_to_float(h):
    """Float of the IEEE half in the low 16 bits of UInt32 ``h``, exact for every finite half (normal:
    exponent rebiased by 112; subnormal: its 10-bit integer times 2^-24, so no flush-to-zero of a subnormal
    float32 bit pattern can change it). Traceable (Dr.Jit)."""
    import drjit as dr

    mi = ensure_variant()
    normal = dr.reinterpret_array(mi.Float, ((h & 0x7FFF) << 13) + (112 << 23))
    magnitude = dr.select((h & 0x7C00) == 0, mi.Float(h & 0x3FF) * (2.0 ** -24), normal)
    return dr.select((h & 0x8000) != 0, -magnitude, magnitude)


def cpu_kernel() -> bool:
    """Whether the renderer lights the exact path's fields with :mod:`.relight_cpu` instead of
    :func:`lit_texels`: on the CPU variants (``llvm_*``) where Numba is importable, unless
    ``MIFACERF_NUMBA_RELIGHT=0``."""
    if not ensure_variant().variant().startswith("llvm"):
        return False
    from .relight_cpu import available

    return available()


def lit_texels(rf_device, n_lights: int, texels: np.ndarray, vertex_ids: np.ndarray, coef: np.ndarray,
               lighting: np.ndarray, light_ids: np.ndarray | None = None, later: bool = False):
    """Lit colour (N, 3) of ``texels`` (N,) rows of a field; ``later``: the kernel is launched and a
    function returned that reads its result back (so a caller can launch every chunk's kernel before
    waiting for the first: Dr.Jit's LLVM kernels run asynchronously until read).

    ``rf_device``: the field's (rows, L, 3) reflectance functions as :class:`HalfWords`
    (:func:`to_device_words`, the fast form) or a flat Dr.Jit Float16 array (:func:`to_device_f16`);
    ``vertex_ids`` (N, 3) and ``coef`` (N, 3) the texels'
    triangle vertices and normalised weights ĉ; ``lighting`` (V, K, 3) per-vertex
    light-stage weights of the lights ``light_ids`` (K,) (default: all L lights, K = L; an array, or a
    :class:`DeviceLighting` shared by the calls that light with it) —
    the lights whose weight is negligible everywhere can be left out of the sum. Both forms give the
    same result bit for bit (the same products, summed in the same order).
    """
    import drjit as dr

    mi = ensure_variant()
    n = len(texels)
    if n == 0:
        empty = np.zeros((0, 3), np.float32)
        return (lambda: empty) if later else empty
    Float, UInt32 = mi.Float, mi.UInt32
    ids = np.arange(n_lights) if light_ids is None else np.asarray(light_ids)
    k = len(ids)
    stride = n_lights * 3
    fast = isinstance(rf_device, HalfWords) and light_ids is None and n_lights % 4 == 0
    if not fast:   # (the four-lights-at-a-time kernel reads none of these: not uploaded for it)
        base_f = to_jit(UInt32, np.asarray(texels, np.uint32) * np.uint32(stride))
        base_v = [to_jit(UInt32, np.asarray(vertex_ids[:, j], np.uint32) * np.uint32(k * 3)) for j in range(3)]
        ids_dev = to_jit(UInt32, np.append(ids, 0).astype(np.uint32))  # padded: never a width-1 (literal) array
    cf = [to_jit(Float, coef[:, j]) for j in range(3)]
    lighting = lighting if isinstance(lighting, DeviceLighting) else DeviceLighting(lighting)
    count = dr.opaque(UInt32, k)

    def cond(i, r, g, b):
        return i < count

    def lam(o, ch):
        light = lighting.flat
        return (cf[0] * dr.gather(Float, light, base_v[0] + o + ch)
                + cf[1] * dr.gather(Float, light, base_v[1] + o + ch)
                + cf[2] * dr.gather(Float, light, base_v[2] + o + ch))

    if fast:
        # four lights at a time: their 12 halves are 3 whole 64-bit words (a row starts at a word), and the
        # lighting is laid out (V, K/4, 3, 4) so that each vertex's 4 values of one channel are 2 words
        UInt64 = mi.UInt64
        words = rf_device.words
        base_w = to_jit(UInt32, np.asarray(texels, np.uint32) * np.uint32(stride // 4))
        base_q = [to_jit(UInt32, np.asarray(vertex_ids[:, j], np.uint32) * np.uint32(k * 3 // 2)) for j in range(3)]
        light_q = lighting.quads
        count = dr.opaque(UInt32, k // 4)

        def floats(w):
            return [dr.reinterpret_array(Float, UInt32(w & 0xFFFFFFFF)), dr.reinterpret_array(Float, UInt32(w >> 32))]

        def body(i, r, g, b):
            halves = []
            for j in range(3):
                w = dr.gather(UInt64, words, base_w + i * 3 + j)
                halves += [UInt32((w >> (16 * e)) & 0xFFFF) for e in range(4)]
            lv = [[floats(dr.gather(UInt64, light_q, base_q[j] + i * 6 + ch * 2))
                   + floats(dr.gather(UInt64, light_q, base_q[j] + i * 6 + ch * 2 + 1)) for ch in range(3)]
                  for j in range(3)]
            acc = [r, g, b]
            for q in range(4):
                for ch in range(3):
                    lam_q = cf[0] * lv[0][ch][q] + cf[1] * lv[1][ch][q] + cf[2] * lv[2][ch][q]
                    acc[ch] = dr.fma(half_to_float(halves[3 * q + ch]), lam_q, acc[ch])
            return (i + 1, *acc)
    elif isinstance(rf_device, HalfWords):
        # any light count or subset: a light's 3 halves lie in 1 or 2 words
        words = rf_device.words

        def body(i, r, g, b):
            o = i * 3
            h = base_f + dr.gather(UInt32, ids_dev, i) * 3
            w0 = dr.gather(mi.UInt64, words, h >> 2)
            w1 = dr.gather(mi.UInt64, words, (h >> 2) + 1, (h & 3) > 1)
            acc = [r, g, b]
            for ch in range(3):
                pos = (h & 3) + ch
                w = dr.select(pos < 4, w0, w1)
                half = UInt32((w >> mi.UInt64((pos & 3) * 16)) & 0xFFFF)
                acc[ch] = dr.fma(half_to_float(half), lam(o, ch), acc[ch])
            return (i + 1, *acc)
    else:
        F16 = type(rf_device)

        def body(i, r, g, b):
            o = i * 3
            of = dr.gather(UInt32, ids_dev, i) * 3
            acc = [r, g, b]
            for ch in range(3):
                f = Float(dr.gather(F16, rf_device, base_f + of + ch))
                acc[ch] = dr.fma(f, lam(o, ch), acc[ch])
            return (i + 1, *acc)

    # Opaque loop state: literal (constant) initial values would bake the wavefront size into
    # the kernel and recompile it for every texel count.
    state = (dr.opaque(UInt32, 0, n), dr.opaque(Float, 0, n), dr.opaque(Float, 0, n), dr.opaque(Float, 0, n))
    _, r, g, b = dr.while_loop(state, cond, body)
    dr.eval(r, g, b)  # one kernel for all three channels

    def result() -> np.ndarray:
        return np.stack([np.asarray(r), np.asarray(g), np.asarray(b)], axis=1)

    result.device = (r, g, b)   # the lit colours left on the device (the renderer places them there)
    return result if later else result()
