"""One pool of host threads for the Numba kernels of a frame (:mod:`.rendering.relight_cpu`,
:mod:`.geometry.raster`): as many threads as Dr.Jit was given cores, so the host's kernels and Dr.Jit's
share the machine alike. The kernels run without the GIL; each call gets disjoint rows to write."""
from __future__ import annotations

_POOL = None


def threads() -> int:
    """Threads a frame's host kernels run on: Dr.Jit's thread count (the cores it was given)."""
    import drjit as dr

    return max(1, int(dr.thread_count()))


def pool():
    """The shared :class:`concurrent.futures.ThreadPoolExecutor` (made on first use)."""
    global _POOL
    if _POOL is None:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = ThreadPoolExecutor(max_workers=threads(), thread_name_prefix="mifacerf-host")
    return _POOL


def run_all(calls: list) -> list:
    """Run the callables ``calls`` on the pool at once (in this thread when there is one) and return their
    results in order; an exception in one is raised here."""
    if len(calls) <= 1 or threads() <= 1:
        return [c() for c in calls]
    return [f.result() for f in [pool().submit(c) for c in calls]]
