"""File helpers shared by every on-disk format: atomic writes, JSON documents, checksums.

Atomic write: the data goes to a temporary file in the destination's folder
(``.<name>.<random>.tmp``), is flushed and fsynced, then renamed over the
destination, so a crash never leaves a half-written file under the final name.
"""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> None:
    """Write ``data`` to ``path`` via a temporary file in the same folder, fsync and rename."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_target(path: Path) -> Path:
    """A temporary path next to ``path`` for writers that need a file name (rename it over ``path``)."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
    return Path(tmp)


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def read_json(path: Path, error: type[Exception], missing: str) -> dict:
    """The JSON document at ``path``; otherwise ``error`` naming the file: ``"<path>: <missing>"`` when
    absent, ``"<path>: not valid JSON (...)"``."""
    if not path.exists():
        raise error(f"{path}: {missing}")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise error(f"{path}: not valid JSON ({exc})") from exc


def read_json_manifest(path: Path, fmt: str, version: int, error: type[Exception], missing: str, what: str) -> dict:
    """The JSON manifest at ``path``, checked to be ``format`` ``fmt`` at ``version``; otherwise ``error``
    naming the file: ``"<path>: <missing>"`` when absent, invalid JSON, or ``"not a version-N <what>"``."""
    meta = read_json(path, error, missing)
    if meta.get("format") != fmt or meta.get("version") != version:
        raise error(f"{path}: not a version-{version} {what}")
    return meta


def write_json_atomic(path: str | os.PathLike, data: dict) -> None:
    atomic_write_bytes(path, (json.dumps(data, indent=1) + "\n").encode())
