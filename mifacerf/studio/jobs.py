"""Registration in the background: "register this expression" (one job at a time, a worker thread).

:func:`register_expression` registers one expression into the capture's registration folder with
the registration's own :class:`~mifacerf.registration.register.Registrar` (the neutral first when it
is not registered yet — everything is registered relative to it), keeping every other registered
expression as it is; re-registering an expression replaces it (``mifacerf register`` without
``--force`` would skip it). Hand fixes in ``hand/overrides.json`` are honoured by the registration
itself (:mod:`mifacerf.registration.overrides`).
"""
from __future__ import annotations

import itertools
import queue
import threading
import time
import traceback
from dataclasses import asdict
from pathlib import Path


def register_expression(capture_root: str | Path, name: str, step=lambda msg, done, total: None) -> Path:
    """Register ``name`` (and the neutral first if needed); returns the registration folder."""
    from ..formats.capture import Capture
    from ..formats.registration import RegisteredExpression
    from ..registration.register import Registrar

    cap = Capture(capture_root)
    out = cap.root / "registration"
    step("reading the hand inputs", 0, 1)
    reg = Registrar(cap, out)
    reg.writer.set_meta("options", asdict(reg.opt))
    reg.writer.set_meta("hand_input_problems", reg.hand.problems)
    T = reg.tpl.n_vertices
    for n in cap.expression_names:
        if n != name and reg.writer.done(n):
            r = RegisteredExpression.load(out / "expressions" / f"{n}.npz", n)
            if len(r.vertices) == T:          # registered with another template: not a reference
                reg.registered[n] = r
    todo = [name] if name == reg.neutral or reg.neutral in reg.registered else [reg.neutral, name]
    if name == reg.neutral:                   # the filter is tuned on the neutral with the current template
        reg.writer.meta.pop("dot_filter", None)
        reg.filter = None
    for k, n in enumerate(todo):
        step(f"registering {n}", k, len(todo) + 1)
        reg.register(n)
    step("eye centres", len(todo), len(todo) + 1)
    reg.finish_eyes()
    return out


class Jobs:
    """A queue of registration jobs run one at a time by a daemon thread."""

    def __init__(self, session):
        self.session = session
        self.jobs: dict[str, dict] = {}
        self._ids = itertools.count(1)
        self._q: queue.Queue = queue.Queue()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="studio-register", daemon=True)
        self._thread.start()

    def submit(self, name: str) -> dict:
        self.session.check_expression(name)
        with self._lock:
            for j in self.jobs.values():     # the same expression already waiting or running: that job
                if j["expression"] == name and j["state"] in ("queued", "running"):
                    return dict(j)
            jid = str(next(self._ids))
            job = {"id": jid, "expression": name, "state": "queued", "step": "waiting", "fraction": 0.0,
                   "submitted": time.time(), "started": None, "finished": None, "elapsed_s": 0.0, "error": None}
            self.jobs[jid] = job
        self._q.put(jid)
        return dict(job)

    def get(self, jid: str) -> dict | None:
        with self._lock:
            j = self.jobs.get(jid)
            if j is None:
                return None
            j = dict(j)
        if j["started"] is not None:
            j["elapsed_s"] = round((j["finished"] or time.time()) - j["started"], 1)
        return j

    def _run(self):
        while True:
            jid = self._q.get()
            job = self.jobs[jid]
            job.update(state="running", started=time.time())

            def step(msg, done, total, job=job):
                job.update(step=msg, fraction=round(done / max(total, 1), 3))

            try:
                register_expression(self.session.root, job["expression"], step)
                self.session.invalidate()
                job.update(state="done", step="done", fraction=1.0)
            except Exception as exc:  # noqa: BLE001 — reported to the page, one line
                job.update(state="failed", error=f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}",
                           trace=traceback.format_exc(limit=8))
            finally:
                job["finished"] = time.time()
                self.session.invalidate()
