"""Single-threaded BLAS for loops of tiny LAPACK calls and small products (blending's fits, a rendered frame).

The fit runs thousands of tiny eigen-problems (60 x 60 Gram matrices, 4 x 4 Horn
matrices).  A multi-threaded OpenBLAS wakes its thread pool for each of them; on
a loaded 2-core machine that makes each call 10-50x slower.  :func:`single_threaded_blas`
limits BLAS to one thread for the duration of a block: through ``threadpoolctl``
when it is installed, otherwise by calling OpenBLAS's own ``*_set_num_threads``
on the OpenBLAS libraries loaded in this process (Linux), otherwise it does
nothing.
"""
from __future__ import annotations

import contextlib
import ctypes

_SET = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads", "openblas_set_num_threads64_",
        "openblas_set_num_threads")
_GET = ("scipy_openblas_get_num_threads64_", "scipy_openblas_get_num_threads", "openblas_get_num_threads64_",
        "openblas_get_num_threads")


_HANDLES = None


def _openblas_handles():
    """(get, set) function pairs of the OpenBLAS libraries loaded now (cached after the first call)."""
    global _HANDLES
    if _HANDLES is None:
        _HANDLES = _find_handles()
    return _HANDLES


def _find_handles():
    out = []
    try:
        with open("/proc/self/maps", encoding="utf-8") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower() and line.rstrip().endswith(".so")
                     or ("openblas" in line.lower() and ".so" in line)}
    except OSError:
        return out
    for p in sorted(paths):
        if not p.startswith("/"):
            continue
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        get = next((getattr(lib, s) for s in _GET if hasattr(lib, s)), None)
        put = next((getattr(lib, s) for s in _SET if hasattr(lib, s)), None)
        if get is not None and put is not None:
            out.append((get, put))
    return out


@contextlib.contextmanager
def single_threaded_blas():
    """Context manager: BLAS/LAPACK run single-threaded inside the block (best effort)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        threadpool_limits = None
    if threadpool_limits is not None:
        with threadpool_limits(limits=1, user_api="blas"):
            yield
        return
    handles = _openblas_handles()
    saved = []
    for get, put in handles:
        try:
            saved.append((put, int(get())))
            put(1)
        except Exception:  # pragma: no cover - exotic builds
            pass
    try:
        yield
    finally:
        for put, n in saved:
            put(n)
