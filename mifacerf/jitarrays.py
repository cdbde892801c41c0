"""NumPy → Dr.Jit array conversion with a stable memory alignment.

Dr.Jit maps NumPy memory into kernels zero-copy and records the pointer's alignment
in the kernel's IR: the same computation fed with a 64-byte-aligned array and with a
16-byte-aligned one compiles to two different kernels (a ~50 ms cache miss each
time the alignment of NumPy's allocation happens to change). :func:`to_jit` always
hands Dr.Jit a 64-byte-aligned buffer, so kernels are compiled once and reused.
"""
from __future__ import annotations

import numpy as np


def aligned_empty(shape, dtype, alignment: int = 64, zeros: bool = False) -> np.ndarray:
    """An uninitialised C-contiguous array of ``shape`` and ``dtype`` whose data pointer is ``alignment``-aligned
    (to be filled in place, e.g. by ``np.concatenate(..., out=)``, and handed to Dr.Jit without another copy).
    ``zeros``: filled with zeros by the allocator (a large buffer's pages are the system's zero pages until
    written, so an image that is mostly left empty costs only what is written)."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    buf = (np.zeros if zeros else np.empty)(nbytes + alignment, np.uint8)
    off = (-buf.ctypes.data) % alignment
    return buf[off:off + nbytes].view(dtype).reshape(shape)


def aligned_zeros(shape, dtype, alignment: int = 64) -> np.ndarray:
    """:func:`aligned_empty` filled with zeros."""
    return aligned_empty(shape, dtype, alignment, zeros=True)


def aligned(array, dtype, alignment: int = 64) -> np.ndarray:
    """A C-contiguous copy of ``array`` as ``dtype`` whose data pointer is ``alignment``-aligned."""
    a = np.asarray(array, dtype)
    out = aligned_empty(a.shape, a.dtype, alignment)
    out[...] = a
    return out


def to_jit(jit_type, array):
    """``jit_type`` (e.g. ``mi.Float``, ``mi.UInt32``, ``mi.Vector3f``) from a NumPy array, via an aligned copy.

    Vector types take a (3, N) array (rows = components). Each component is uploaded on its own: a
    vector built from one 2-D array gathers its rows from a flat buffer at offsets N and 2N, literals
    baked into the kernel, so every new N (the samples of a frame) compiled new kernels.
    """
    import drjit as dr

    dtype = {dr.VarType.Float32: np.float32, dr.VarType.Float16: np.float16, dr.VarType.Float64: np.float64,
             dr.VarType.UInt32: np.uint32, dr.VarType.Int32: np.int32, dr.VarType.Bool: np.bool_,
             dr.VarType.UInt64: np.uint64, dr.VarType.Int64: np.int64}[dr.type_v(jit_type)]
    a = np.asarray(array)
    if dr.depth_v(jit_type) > 1 and a.ndim == 2:
        component = dr.value_t(jit_type)
        return jit_type(*[component(aligned(row, dtype)) for row in a])
    return jit_type(aligned(a, dtype))


def from_jit(vec) -> np.ndarray:
    """A Dr.Jit array → NumPy; vector types (Color3f, Vector3f, …) of width N become (N, components)."""
    import drjit as dr

    if dr.depth_v(vec) > 1:   # component by component: np.asarray(vec) scatters rows at literal offsets N, 2N
        dr.eval(vec)          # one kernel for all components (read back one by one, each would be its own)
        return np.stack([np.asarray(vec[i]) for i in range(len(vec))], axis=1)
    return np.asarray(vec)
