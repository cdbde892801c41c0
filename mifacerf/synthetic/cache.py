"""On-disk cache for the expensive, deterministic parts of the synthetic subject's build.

Files live under ``$MIFACERF_CACHE`` (or ``~/.cache/mifacerf``) in ``synthetic/``, named by a key
that includes :data:`SUBJECT_VERSION`; bump the version whenever geometry, atlas or texture code
changes so stale files are never used. Writes are atomic (temporary file + rename).
"""
from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import numpy as np

from ..formats.files import user_cache_dir

#: bump when anything that feeds a cached result changes
SUBJECT_VERSION = "head-v9"


def cache_dir() -> Path:
    d = user_cache_dir() / "synthetic"
    d.mkdir(parents=True, exist_ok=True)
    return d


def key(*parts) -> str:
    h = hashlib.sha1(repr((SUBJECT_VERSION,) + parts).encode()).hexdigest()[:16]
    return f"{SUBJECT_VERSION}-{h}"


def load(name: str):
    """The cached dict of arrays for ``name``, or None."""
    path = cache_dir() / f"{name}.npz"
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception:  # a corrupt or partial file: rebuild
        return None


def save(name: str, **arrays) -> None:
    d = cache_dir()
    fd, tmp = tempfile.mkstemp(dir=d, suffix=".npz.tmp")
    os.close(fd)
    try:
        with open(tmp, "wb") as f:
            np.savez(f, **arrays)
        os.replace(tmp, d / f"{name}.npz")
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def cached(name: str, build):
    """``load(name)`` or ``build()`` (a dict of arrays) saved under ``name``."""
    out = load(name)
    if out is None:
        out = build()
        try:
            save(name, **out)
        except OSError:
            pass
    return out
