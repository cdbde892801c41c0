#!/usr/bin/env python
"""Measure the stages on the execution layer with 1 and 2 local workers (docs/distributed.md).

    .venv/bin/python scripts/measure_distributed.py OUT [--stages overhead,synth,build,compress,evaluate,drive,paper_take]
                                                        [--track TRACK --model MODEL --frames 0:12]

Each stage runs in one process (``--workers 1``: no Dask) and on a fresh local cluster of 2 worker processes,
twice each (cold: the workers import, load and compile; then warm, the same work again); it records the units,
the wall time of both runs (the cluster's start-up apart), the peak
resident memory of the workers, the output's size on disk, and whether the outputs are byte-identical.
One JSON line per (stage, workers) is appended to OUT/measurements.jsonl (with the machine's load average,
which other programs may dominate). Stages: ``overhead`` (400 empty units: the scheduler's cost per unit),
``synth`` (the tiny preset, 3 expressions: 9 takes), ``build`` and ``compress`` (a model of that capture,
registered once in one process), ``evaluate`` (render cases n=1, gradient, 48 px, 16-spp truths), ``drive``
(TRACK driven by MODEL, --frames, interior, a --cache-gb field cache per process), ``paper_take`` (one take of the paper preset: 480 lights, one
480-px camera, 9 spp, one process only: the synth unit cost at paper scale), ``small_drive`` (a 0.4 s
performance of the tiny capture recorded, tracked once and driven by the ``build`` model: 24 frames).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import sys
import time
from pathlib import Path

EXPRESSIONS = ["neutral", "smile", "viseme_aa"]


def noop(context, item):
    return item


def peak_rss_bytes() -> int:
    """This process's peak resident memory (Linux VmHWM; getrusage's ru_maxrss survives exec, so a spawned
    worker would report its parent's peak)."""
    from mifacerf.evaluation.bench import vm_hwm

    return vm_hwm()


def digest(folder: Path, skip=("drive.json",)) -> str:
    h = hashlib.sha256()
    for p in sorted(Path(folder).rglob("*")):
        if p.is_file() and p.name not in skip and not p.name.endswith(".lock"):
            h.update(p.relative_to(folder).as_posix().encode())
            h.update(p.read_bytes())
    return h.hexdigest()[:16]


def du(folder: Path) -> int:
    return sum(p.stat().st_size for p in Path(folder).rglob("*") if p.is_file())


def run_stage(name, workers, fn, out: Path, record):
    from mifacerf.execution import open_executor

    t0 = time.perf_counter()
    ex = open_executor(workers)
    start = time.perf_counter() - t0
    try:
        t0 = time.perf_counter()
        if name != "paper_take":    # (one paper take is measured once, cold)
            fn(ex, out / f"{name}-w{workers}-cold")    # cold: workers import, load models, build scenes, compile
        cold = time.perf_counter() - t0
        t0 = time.perf_counter()
        units, folder = fn(ex, out / f"{name}-w{workers}")   # warm: the same work again on the same workers
        seconds = time.perf_counter() - t0
        peak = max(ex.client.run(peak_rss_bytes).values()) if ex.distributed else peak_rss_bytes()
    finally:
        ex.close()
    row = {"stage": name, "workers": workers, "units": units, "seconds": round(seconds, 2), "cold_seconds": round(cold, 2),
           "cluster_start_s": round(start, 2), "seconds_per_unit": round(seconds / max(units, 1), 4),
           "peak_rss_mb_per_process": round(peak / 2**20), "load_average": os.getloadavg(),
           "disk_mb": round(du(folder) / 1e6, 2) if folder is not None and Path(folder).exists() else None,
           "digest": digest(folder) if folder is not None and Path(folder).exists() else None}
    record(row)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--stages", default="overhead,synth,build,compress,evaluate")
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--track", default=None)
    ap.add_argument("--model", default=None)
    ap.add_argument("--frames", default="0:12")
    ap.add_argument("--cache-gb", type=float, default=1.5, help="drive: the model's field cache per process")
    a = ap.parse_args()
    out = a.out
    out.mkdir(parents=True, exist_ok=True)
    log = out / "measurements.jsonl"

    def record(row):
        print(json.dumps(row), flush=True)
        with open(log, "a") as f:
            f.write(json.dumps(row) + "\n")

    def overhead(ex, _):
        ex.map(noop, range(10))   # warm: the workers import what a unit needs
        ex.map(noop, range(400))
        return 400, None

    def synth(ex, folder):
        from mifacerf.synthetic.synth import synthesize

        shutil.rmtree(folder, ignore_errors=True)
        synthesize(folder, preset="tiny", expressions=EXPRESSIONS, progress=False, executor=ex)
        return len(EXPRESSIONS) * 3, folder / "capture" / "images"

    def registered():
        """A copy of the 1-worker synth's tiny capture, registered once (one process; reused: OUT/registered)."""
        from mifacerf.registration import register_capture

        cap = out / "registered" / "capture"
        if not (cap / "registration" / "registration.json").exists():
            shutil.rmtree(out / "registered", ignore_errors=True)
            shutil.copytree(out / "synth-w1", out / "registered")
            t0 = time.perf_counter()
            register_capture(cap, progress=False)
            record({"stage": "register", "workers": 1, "units": len(EXPRESSIONS),
                    "seconds": round(time.perf_counter() - t0, 2), "load_average": os.getloadavg(),
                    "note": "sequential: each expression's coarse morph starts from the ones registered before"})
        return cap

    def build(ex, folder):
        import inspect

        from mifacerf.rendering.build import build_model

        cap = registered()
        shutil.rmtree(folder, ignore_errors=True)
        kw = {"executor": ex} if "executor" in inspect.signature(build_model).parameters else {}
        build_model(cap, folder, progress=False, **kw)
        return len(EXPRESSIONS) * 3, folder

    def model_copy(folder):
        src = out / "build-w1"
        if not (src / "model.json").exists():
            build(__import__("mifacerf.execution").execution.Executor(), src)
        shutil.rmtree(folder, ignore_errors=True)
        shutil.copytree(src, folder, ignore=shutil.ignore_patterns("*.pca*", "*.sh*"))
        return folder

    def compress(ex, folder):
        from mifacerf.rendering.compression import compress_model
        from mifacerf.rendering.model import Model

        info = compress_model(Model(model_copy(folder)), [4, 8], progress=False, executor=ex)
        return info["fields"], folder

    def evaluate(ex, folder):
        from mifacerf.evaluation.render_cases import evaluate as ev

        model = out / "build-w1"
        if not (model / "model.json").exists():
            model_copy(out / "build-w1-copy")
            model = out / "build-w1-copy"
        folder.mkdir(parents=True, exist_ok=True)
        report = ev(out / "synth-w1", model, envs=("gradient",), n=1, seed=3, spp_truth=16, size=48, progress=False,
                    pictures=folder / "cases.png", executor=ex)
        (folder / "cases.json").write_text(json.dumps(
            [{k: v for k, v in c.items() if k not in ("seconds", "stages")} for c in report["cases"]], sort_keys=True))
        return len(report["cases"]), folder

    def drive(ex, folder):
        from mifacerf.tracking.drive import drive as dr

        from mifacerf.rendering.api import load_model

        a_, b_ = (int(x) for x in a.frames.split(":"))
        shutil.rmtree(folder, ignore_errors=True)
        face = load_model(a.model, int(a.cache_gb * 2**30))   # workers get the same field cache size
        dr(a.track, face, folder, envs=("interior",), frames=(a_, b_), progress=False, executor=ex)
        return b_ - a_, folder

    def small_drive(ex, folder):
        """A 0.4 s performance (24 frames) of the tiny capture, tracked and driven by its model (the tests' world)."""
        from mifacerf.synthetic.recording import record_performance
        from mifacerf.tracking.drive import drive as dr
        from mifacerf.tracking.track import track_performance

        registered()
        model = out / "build-w1"
        if not (model / "model.json").exists():
            build(__import__("mifacerf.execution").execution.Executor(), model)
        track = out / "registered" / "performance" / "track"
        if not (track / "track.npz").exists():
            perf = record_performance(out / "registered", 0.4, size=None, progress=False)
            track_performance(perf, track, model=model, progress=False)
        shutil.rmtree(folder, ignore_errors=True)
        dr(track, model, folder, envs=("interior",), progress=False, executor=ex)
        return 24, folder

    def paper_take(ex, folder):
        from mifacerf.rig import Rig, preset
        from mifacerf.synthetic.synth import synthesize

        rig = preset("paper").rig()
        shutil.rmtree(folder, ignore_errors=True)
        synthesize(folder, preset="paper", expressions=["neutral"], progress=False, rig=Rig(rig.lights, rig.cameras[:1]),
                   executor=ex)
        return 1, folder / "capture" / "images"

    stages = {"overhead": overhead, "synth": synth, "build": build, "compress": compress, "evaluate": evaluate,
              "drive": drive, "small_drive": small_drive, "paper_take": paper_take}
    for name in a.stages.split(","):
        for w in ([1] if name == "paper_take" else [int(x) for x in a.workers.split(",")]):
            run_stage(name, w, stages[name], out, record)


if __name__ == "__main__":
    sys.exit(main())
