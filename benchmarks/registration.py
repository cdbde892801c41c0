"""Registration time of a capture: wall and CPU seconds of ``register_capture`` into a scratch folder.

    python benchmarks/registration.py CAPTURE [--expressions a,b] [--repeat 2] [--json OUT.json]

Each repeat registers the capture from scratch into a new temporary folder (the capture's own
``registration/`` is not touched; its proxies cache ``CAPTURE/cache`` is reused or filled), then deletes
it. Prints, per repeat, the wall and CPU seconds (CPU: this process and its threads, so a thread pool
shows as CPU > wall on idle cores) and the machine's load average before and after: on a shared machine
compare runs side by side.
To compare two versions of the code, run this once per version in alternation (e.g.
``PYTHONPATH=<other checkout> python benchmarks/registration.py ...``).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("capture")
    ap.add_argument("--expressions", default=None, help="comma-separated (default: all; the neutral first)")
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)

    from mifacerf.registration import register_capture

    expressions = a.expressions.split(",") if a.expressions else None
    runs = []
    for _ in range(max(1, a.repeat)):
        scratch = tempfile.mkdtemp(prefix="mifacerf-regbench-")
        try:
            load0 = os.getloadavg()[0]
            t, c = time.perf_counter(), time.process_time()
            register_capture(a.capture, out=os.path.join(scratch, "registration"), expressions=expressions,
                             progress=False)
            run = {"wall_s": round(time.perf_counter() - t, 2), "cpu_s": round(time.process_time() - c, 2),
                   "load_before": round(load0, 2), "load_after": round(os.getloadavg()[0], 2)}
        finally:
            shutil.rmtree(scratch, ignore_errors=True)
        runs.append(run)
        print(f"register {a.capture}: {run['wall_s']:.1f} s wall, {run['cpu_s']:.1f} s CPU "
              f"(load {run['load_before']} -> {run['load_after']}, {os.cpu_count()} CPUs)", flush=True)
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"capture": a.capture, "expressions": expressions, "runs": runs}, f, indent=1)


if __name__ == "__main__":
    main()
