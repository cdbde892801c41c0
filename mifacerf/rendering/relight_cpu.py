"""The exact relight sum on the CPU, one texel at a time, vectorised along its lights (Numba).

The same sum as :func:`.relight.lit_texels` (paper Fig. 7, third row), for every chunk of a frame::

    T(x) = Σ_l F(x)[l] ⊙ Σ_k ĉ_k L_{v_k}[l],      ĉ_k = b_k a_{v_k} / Σ_j b_j a_{v_j}

laid out the other way round. Dr.Jit's kernel puts one texel in each SIMD lane, so every read of a
field row and of a vertex's lighting is a gather; on the AVX-512 cores measured the gathers, not the
arithmetic, bound it. Here one call walks a texel's row of L × 3 float16 values *contiguously*, with its
three vertices' lighting rows beside it: plain vector loads, the halves decoded exactly (the values of
:func:`.relight.half_to_float`'s rule, subnormals included) where they are read, by LLVM's own half → float
widening (one ``vcvtph2ps`` per 16 halves on x86 with F16C; :func:`._numba_kernels._half`), 48 partial sums
(3 channels × 16 lanes) so that nothing needs reassociating. The sums are added in another order than
Dr.Jit's, so the two agree to float32 rounding (images 150 dB apart), not bit for bit.

:func:`lit_images` also takes over the chunk loop's texel selection in NumPy (the texels whose
weight Σ b a is positive, their ĉ): the kernel tests each texel of the field itself. A frame's chunks are
cut into work items of :data:`WORK_ROWS` rows (more where rows are short) and lit by :func:`threads`
Python threads (:mod:`mifacerf.hostpool`), each calling the serial kernel without the GIL (one parallel
Numba launch per chunk cost more than the light sum of a small chunk; 113 chunks a drive frame). The images are made on the host and handed to Dr.Jit once.

Used by ``Renderer.light_frame`` for the ``exact`` method on the ``llvm_*`` variants when Numba is
importable (:func:`.relight.cpu_kernel`; ``MIFACERF_NUMBA_RELIGHT=0`` keeps Dr.Jit's kernel); the CUDA
variants keep Dr.Jit's (a GPU is built for its gathers). Numba is imported on first use and the kernel
compiled once and cached on disk (``cache=True``: next to this file, or Numba's user cache where that is
not writable): the first process compiles it (~1.5 s), later ones load it (~0.4 s with Numba's import).
Measured: docs/rendering.md, "Sixth pass".
"""
from __future__ import annotations

import numpy as np

from ..hostpool import run_all, threads  # noqa: F401  (threads: the count that lights a frame's chunks)

_KERNELS = None
_UNAVAILABLE = None     # the reason Numba cannot be used, once found


def available() -> bool:
    """Whether the CPU kernel can be used here (Numba importable, not switched off)."""
    from ..formats.files import switched_off

    if switched_off("MIFACERF_NUMBA_RELIGHT"):
        return False
    return _kernels() is not None


def kernels() -> dict | None:
    """The Numba kernels by name (``rows``: the relight sum; ``trilinear``: the rotated light basis' node
    blend), or None where Numba is not importable or ``MIFACERF_NUMBA_RELIGHT=0``."""
    return _kernels() if available() else None


def _kernels():
    global _KERNELS, _UNAVAILABLE
    if _KERNELS is not None or _UNAVAILABLE is not None:
        return _KERNELS
    try:
        import numba  # noqa: F401  (the kernels' module imports it; here: is it there)
    except ImportError as e:      # an optional speed-up: Dr.Jit's kernel serves without it
        _UNAVAILABLE = str(e)
        return None
    from . import _numba_kernels as k

    _KERNELS = {"rows": k.lit_rows, "trilinear": k.trilinear_rows}
    return _KERNELS


#: rows of a field per work item of :func:`lit_images` (so that the threads share a frame's large and
#: small chunks evenly), for rows of :data:`WORK_VALUES` / WORK_ROWS halves (the exact path's 192 lights × 3);
#: shorter rows (``sh``, ``pca``: 27–75 values) make proportionally longer items, so that each item's Python
#: dispatch (~20 µs) stays small beside its work
WORK_ROWS = 2048
WORK_VALUES = WORK_ROWS * 576


def check_map(bary, fv, lin, cov, n_vertices: int, pixels: int) -> tuple:
    """A texel map in the forms :func:`lit_images` reads, its indices checked (a ValueError naming the
    one out of range): bary (N, 3) float32, vertex ids (N, 3) int64 below ``n_vertices``, pixel index (N,)
    int64 below ``pixels``, coverage (N,) float32."""
    out = (np.ascontiguousarray(bary, np.float32), np.ascontiguousarray(fv, np.int64),
           np.ascontiguousarray(lin, np.int64), np.ascontiguousarray(cov, np.float32))
    b, v, p, c = out
    if b.ndim != 2 or b.shape[1] != 3 or v.shape != b.shape or p.shape != c.shape or len(p) != len(b):
        raise ValueError(f"texel map of shapes bary {b.shape}, vertex ids {v.shape}, pixels {p.shape}, "
                         f"coverage {c.shape}: expected (N, 3), (N, 3), (N,), (N,)")
    if len(v) and (v.min() < 0 or v.max() >= n_vertices):
        raise ValueError(f"texel map: vertex ids {v.min()}..{v.max()} outside the mesh's {n_vertices} vertices")
    if len(p) and (p.min() < 0 or p.max() >= pixels):
        raise ValueError(f"texel map: pixel indices {p.min()}..{p.max()} outside the image's {pixels} pixels")
    return out


def lit_images(fields: list, lights: list, chunk_light, weights: np.ndarray, maps: list, sizes,
               light_ids: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Every chunk's lit image of a frame, made on the host: the work of ``Renderer.light_frame``'s chunk
    loop and of :func:`.relight.lit_texels` for each chunk, fused; the chunks' rows split into work items
    of :data:`WORK_ROWS`, lit by :func:`threads` threads at once.

    Per chunk c: ``fields[c]`` its field (rows, L, 3) float16 (host, e.g. memory-mapped); ``maps[c]`` its
    texel map (bary (rows, 3) float32, vertex ids (rows, 3) int64, pixel index (rows,) int64, coverage
    (rows,) float32); ``weights[c]`` (T,) float64 its vertex weights (both tiers: a texel is lit where
    Σ_k b_k a_{v_k} > 0, with ĉ_k = b_k a_{v_k} / Σ); ``sizes[c]`` its image's pixels;
    ``lights[chunk_light[c]]`` (V, K·3) float32, contiguous, the lighting of its source for the lights
    ``light_ids`` (K,) (None: all L). Returns the images (4·Σ sizes,) float32 — RGB and coverage per
    pixel, chunk after chunk, 0 where no texel is lit, as :func:`.renderer._lit_images` lays them out —
    and the texels lit per chunk (C,) int64.

    The kernel does not check indices: the vertex ids must lie below the rows of ``weights`` and of the
    lighting, the pixel indices below ``sizes[c]`` (:func:`check_map` checks a texel map once; the
    renderer does so when it first reads a field). Shapes are checked here."""
    from ..jitarrays import aligned_zeros

    kern = _kernels()
    if kern is None:
        raise RuntimeError(f"the CPU relight kernel needs Numba: {_UNAVAILABLE}")
    sizes = np.asarray(sizes, np.int64)
    images = aligned_zeros((4 * int(sizes.sum()),), np.float32)
    ids = np.zeros(0, np.int64) if light_ids is None else np.asarray(light_ids, np.int64)
    W = np.ascontiguousarray(weights, np.float64)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]) if len(sizes) else sizes
    args, items = [], []
    for c, (field, (bary, fv, lin, cov)) in enumerate(zip(fields, maps)):
        rows = len(bary)
        f = np.asarray(field).reshape(rows, -1).view(np.uint16)
        light = lights[chunk_light[c]]
        if not (len(fv) == len(lin) == len(cov) == rows and light.shape[0] == W.shape[1]):
            raise ValueError(f"chunk {c}: texel map of {rows}/{len(fv)}/{len(lin)}/{len(cov)} rows, lighting of "
                             f"{light.shape[0]} vertices for weights of {W.shape[1]}")
        if light.shape[1] != (3 * len(ids) if len(ids) else f.shape[1]):
            raise ValueError(f"chunk {c}: lighting of {light.shape[1]} values a vertex for a field of "
                             f"{f.shape[1]} a row and {len(ids)} lights kept")
        args.append((f, light, ids, bary, fv, lin, cov, W[c], images, int(offsets[c])))
        step = max(WORK_ROWS, WORK_VALUES // max(f.shape[1], 1))
        items += [(c, a, min(a + step, rows)) for a in range(0, rows, step)]
    counts = np.zeros(len(items), np.int64)
    todo = iter(enumerate(items))
    run = kern["rows"]

    def work():
        for i, (c, a, b) in todo:          # next() under the GIL: each item taken once
            counts[i] = run(*args[c], a, b)

    run_all([work] * min(threads(), len(items)))
    lit = np.bincount([c for c, _, _ in items], weights=counts, minlength=len(args)).astype(np.int64)
    return images, lit
