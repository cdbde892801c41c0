"""Steps that are skipped when their inputs have not changed, by content digests (not modification times).

A job (``mifacerf demo``) keeps ``OUT/steps.json``: for each step the digest of its inputs, the digest of
its outputs and its result (a JSON value, e.g. the metrics it computed). :meth:`Steps.run` skips a step —
without calling it, without writing anything — when the recorded input digest equals the current one and
every output is present with its recorded digest; otherwise it runs the step and records it.

Digests (:func:`digest`): a file by its bytes; a folder that carries a manifest (``model.json``,
``registration.json``, ``manifest.json``, which list the sha256 of every other file) by that manifest's
bytes — cheap, and as exact as the manifest; any other folder by the relative names and bytes of all its
files (lock files and transaction leftovers, ``.*``, excluded); any other value by its JSON text. A
missing path digests as ``missing``.
"""
from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

from .formats.files import write_json_atomic

MANIFESTS = ("model.json", "registration.json", "manifest.json")
RECORD = "steps.json"
FORMAT, VERSION = "mifacerf.steps", 1


def _file_digest(h, path: Path) -> None:
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)


def digest(*items) -> str:
    """sha256 hex of ``items``: paths (files or folders, see the module doc) and JSON values, in order."""
    h = hashlib.sha256()
    for item in items:
        if isinstance(item, Path):
            h.update(f"\0path:{item.name}\0".encode())
            if not item.exists():
                h.update(b"missing")
            elif item.is_file():
                _file_digest(h, item)
            else:
                manifest = next((item / m for m in MANIFESTS if (item / m).is_file()), None)
                if manifest is not None:
                    _file_digest(h, manifest)
                else:
                    for p in sorted(item.rglob("*")):
                        rel = p.relative_to(item)
                        if p.is_file() and not any(part.startswith(".") for part in rel.parts):
                            h.update(f"\0{rel.as_posix()}\0".encode())
                            _file_digest(h, p)
        else:
            h.update(("\0value:" + json.dumps(item, sort_keys=True, default=str)).encode())
    return h.hexdigest()


def _jsonable(value):
    """``value`` as it reads back from JSON (NumPy scalars and arrays become numbers and lists)."""
    def default(o):
        if hasattr(o, "tolist"):
            return o.tolist()
        return float(o)
    return json.loads(json.dumps(value, default=default))


class Steps:
    """The step record of a job folder; ``log(message)`` hears which steps are skipped."""

    def __init__(self, out: str | Path, log=None):
        self.out = Path(out)
        self.path = self.out / RECORD
        self.log = log or (lambda message: None)
        try:
            data = json.loads(self.path.read_text())
            self.record = data["steps"] if data.get("format") == FORMAT else {}
        except (OSError, ValueError, KeyError, TypeError):
            self.record = {}          # none yet, or damaged: every step runs (and the record is rewritten)
        self.skipped: list[str] = []

    def up_to_date(self, name: str, inputs: list, outputs: list[Path]) -> bool:
        rec = self.record.get(name)
        return bool(rec) and rec.get("inputs") == digest(*inputs) and all(p.exists() for p in outputs) \
            and rec.get("outputs") == digest(*outputs)

    def run(self, name: str, inputs: list, outputs: list[Path], fn, *args, **kwargs):
        """``fn(*args, **kwargs)`` unless step ``name`` is up to date; returns its (recorded) result."""
        if self.up_to_date(name, inputs, outputs):
            self.skipped.append(name)
            self.log(f"   up to date (inputs unchanged): {name}")
            return self.record[name].get("result")
        t0 = time.perf_counter()
        result = _jsonable(fn(*args, **kwargs))
        self.record[name] = {"inputs": digest(*inputs), "outputs": digest(*outputs), "result": result,
                             "seconds": round(time.perf_counter() - t0, 3)}
        write_json_atomic(self.path, {"format": FORMAT, "version": VERSION, "steps": self.record})
        return result

    def seconds(self, name: str) -> float | None:
        """The run time recorded for step ``name`` (the run that made its outputs)."""
        rec = self.record.get(name)
        return None if rec is None else rec.get("seconds")
