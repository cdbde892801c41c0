"""The session journal: ``CAPTURE/session.jsonl``, append-only, one fsynced record per line.

Each line is ``<crc32 hex8> <json>\\n``; the CRC covers the JSON text. A reader
skips (and reports) a line whose CRC or JSON is bad — the torn last line of a
session killed mid-write, or bit rot — and never rewrites the file: every record
the session needs can be re-derived from the files on disk (an image whose
record was lost is re-adopted after it verifies), so a lost line costs time,
never data.

Records are dicts with an ``event`` key (see :mod:`mifacerf.capture.session` for the
list) and ``t``, the wall-clock time in seconds since the epoch.
"""
from __future__ import annotations

import json
import os
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

from ..formats.files import fsync_dir
from ..errors import MifacerfError


class JournalError(MifacerfError, RuntimeError):
    """The journal cannot be read or written (the message names the file and line)."""


def _line(record: dict) -> bytes:
    text = json.dumps(record, sort_keys=True, separators=(",", ":"))
    return f"{zlib.crc32(text.encode()):08x} {text}\n".encode()


@dataclass
class JournalContents:
    records: list[dict] = field(default_factory=list)
    bad_lines: list[int] = field(default_factory=list)  # 1-based line numbers skipped


def read_journal(path: str | os.PathLike) -> JournalContents:
    """All valid records of the journal at ``path`` (bad lines skipped and listed)."""
    path = Path(path)
    out = JournalContents()
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise JournalError(f"{path}: no session journal here") from None
    for i, raw in enumerate(data.split(b"\n"), start=1):
        if not raw.strip():
            continue
        try:
            crc, text = raw.decode().split(" ", 1)
            if int(crc, 16) != zlib.crc32(text.encode()):
                raise ValueError("CRC mismatch")
            rec = json.loads(text)
            if not isinstance(rec, dict) or "event" not in rec:
                raise ValueError("not a record")
        except (ValueError, UnicodeDecodeError):
            out.bad_lines.append(i)
            continue
        out.records.append(rec)
    return out


class Journal:
    """Appends records to ``path``, each flushed and fsynced before :meth:`append` returns."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        new = not self.path.exists()
        self._f = open(self.path, "ab")
        if new:
            fsync_dir(self.path.parent)
        elif self.path.stat().st_size:
            with open(self.path, "rb") as f:  # a torn last line: start ours on a fresh line
                f.seek(-1, os.SEEK_END)
                if f.read(1) != b"\n":
                    self._write(b"\n")

    def _write(self, data: bytes) -> None:
        self._f.write(data)
        self._f.flush()
        os.fsync(self._f.fileno())

    def append(self, event: str, **data) -> dict:
        rec = {"event": event, "t": round(time.time(), 3), **data}
        self._write(_line(rec))
        return rec

    def close(self) -> None:
        if not self._f.closed:
            self._f.close()

    def __enter__(self) -> "Journal":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
