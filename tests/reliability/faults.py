"""Fault injection for the reliability tests: folder snapshots, a child process killed with SIGKILL at a
chosen moment, an injected ENOSPC.

``python tests/reliability/faults.py JOB ARGS_JSON KILL`` runs one job in a child (``build``, ``register``,
``compress``; ``drive`` and ``demo`` with the stand-ins of :mod:`stand_ins`; ``output``: an OutputFolder
of a few files; ``replace``: formats.files.replace_together of temporary files, as ``render -o`` does).
KILL is ``none``, ``time:SECONDS`` (SIGKILL itself that long after it starts the job) or
``call:NAME:N[:FILTER]`` (SIGKILL itself just before the N-th call of ``os.NAME`` whose arguments contain
FILTER, or ``WANTED!UNWANTED``: contain WANTED but not UNWANTED — a precise crash point between two
renames). The child prints ``ready`` once imported.
"""
from __future__ import annotations

import errno
import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path


def snapshot(folder: Path) -> dict[str, bytes]:
    """{relative path: bytes} of every file under ``folder`` (the lock file lies beside it)."""
    folder = Path(folder)
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def siblings(folder: Path) -> list[str]:
    """Leftovers of folder transactions beside ``folder`` (``.<name>.building-*`` and the like)."""
    folder = Path(folder)
    return sorted(n for n in os.listdir(folder.parent) if n.startswith(f".{folder.name}.")
                  and not n.endswith(".lock"))


def run_child(job: str, args: dict, kill: str = "none", timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, __file__, job, json.dumps(args), kill], capture_output=True,
                          text=True, timeout=timeout)


def start_child(job: str, args: dict, kill: str = "none") -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, job, json.dumps(args), kill], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def killed(proc) -> bool:
    return proc.returncode == -signal.SIGKILL


def hold_lock(folder, error, **kw):
    """A thread holding ``folder``'s FolderLock (flock treats another thread's descriptor as another holder,
    as another process would be; ``kw`` for FolderLock); returns the function that releases it."""
    from mifacerf.formats.files import FolderLock

    held, done = threading.Event(), threading.Event()

    def hold():
        with FolderLock(folder, error, **kw):
            held.set()
            done.wait(60)
    t = threading.Thread(target=hold)
    t.start()
    held.wait(30)
    return lambda: (done.set(), t.join())


class ENOSPC:
    """``monkeypatch.setattr(os, "fsync", ENOSPC(n))``: the n-th fsync of a file fails with 'No space left on
    device' (every atomic write fsyncs its file before the rename)."""

    def __init__(self, n: int = 1):
        self.n, self.calls, self._fsync = n, 0, os.fsync

    def __call__(self, fd):
        import stat

        if not stat.S_ISREG(os.fstat(fd).st_mode):      # (folders' fsyncs are not writes)
            return self._fsync(fd)
        self.calls += 1
        if self.calls == self.n:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self._fsync(fd)


# ------------------------------------------------------------------ the child
def _arm(kill: str) -> None:
    if kill == "none":
        return
    if kill.startswith("time:"):
        delay = float(kill.split(":", 1)[1])
        threading.Timer(delay, lambda: os.kill(os.getpid(), signal.SIGKILL)).start()
        return
    _, name, n, *flt = kill.split(":", 3)
    n, flt = int(n), (flt[0] if flt else "")
    want, _, unwanted = flt.partition("!")
    real = getattr(os, name)
    count = [0]

    def wrapped(*a, **kw):
        text = " ".join(map(str, a))
        if want in text and not (unwanted and unwanted in text):
            count[0] += 1
            if count[0] == n:
                os.kill(os.getpid(), signal.SIGKILL)
        return real(*a, **kw)

    setattr(os, name, wrapped)


def _main(job: str, args: dict, kill: str) -> None:
    import mifacerf.formats.files  # noqa: F401  (imports first: the kill is armed for the job alone)
    if job == "build":
        from mifacerf.rendering.build import build_model
    elif job == "compress":
        from mifacerf.rendering.compression import compress_model
        from mifacerf.rendering.model import Model
    elif job == "demo":
        import mifacerf.demo  # noqa: F401
        from stand_ins import run_demo
    elif job == "drive":
        from stand_ins import run_drive
    elif job == "output":
        from mifacerf.formats.files import OutputFolder
    elif job == "replace":
        from mifacerf.formats.files import replace_together
    else:
        from mifacerf.registration import register_capture
        from mifacerf.variant import ensure_variant

        ensure_variant()
    print("ready", flush=True)
    _arm(kill)
    if job == "build":
        build_model(progress=False, **args)
    elif job == "register":
        register_capture(progress=False, **args)
    elif job == "compress":
        compress_model(Model(args["model"]), args["ranks"], progress=False, method="pca")
    elif job == "demo":
        run_demo(**args)
    elif job == "drive":
        run_drive(**args)
    elif job == "output":          # an OutputFolder of a few files, the old folder's 'keep*' entries carried
        o = OutputFolder(args["target"], "done.json", what="test", carry=lambda name: name.startswith("keep"))
        for rel, text in args["files"].items():
            (o.root / rel).parent.mkdir(parents=True, exist_ok=True)
            (o.root / rel).write_text(text)
        (o.root / "done.json").write_text("{}")
        o.finish()
    elif job == "replace":         # the files of 'mifacerf render -o' (temporary -> final) renamed together
        replace_together(args["pairs"], args["journal"])
    else:
        raise SystemExit(f"unknown job {job}")
    print("done", flush=True)
    os._exit(0)          # (no Timer thread left to wait for)


if __name__ == "__main__":
    _main(sys.argv[1], json.loads(sys.argv[2]), sys.argv[3])
