"""Checksum stamps (``formats/files.check_entry``) on and off, side by side, alternating: fresh processes
that (1) import mifacerf, open MODEL and render one 256² frame (``speed.cold``), and (2) with ``--track``,
drive the first ``--frames`` frames of TRACK with ``mifacerf drive --workers 1 --env sky --no-exr``.
``MIFACERF_CHECKSUM_STAMPS=0`` (off) checksums every file a process reads; on, a file stamped by an earlier
process is trusted from its stat data. One warm-up pass of each first (page cache, and the stamps)::

    python benchmarks/checksum_stamps.py mifacerf-demo/model [--track mifacerf-demo/performance/track]
        [--frames 30] [--repeats 2]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import speed  # noqa: E402


def drive(model: str, track: str, frames: int, env: dict) -> float:
    mifacerf = Path(sys.executable).with_name("mifacerf")
    with tempfile.TemporaryDirectory() as out:
        t = time.perf_counter()
        subprocess.run([str(mifacerf), "drive", track, "--model", model, "-o", str(Path(out) / "drive"), "--frames",
                        str(frames), "--workers", "1", "--env", "sky", "--no-exr"], env=env, check=True,
                       capture_output=True)
        return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("model")
    ap.add_argument("--track")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeats", type=int, default=2)
    a = ap.parse_args()
    rows = {"off": {"cold": [], "drive": []}, "on": {"cold": [], "drive": []}}
    for rep in range(a.repeats + 1):
        for name, value in (("off", "0"), ("on", "1")):
            os.environ["MIFACERF_CHECKSUM_STAMPS"] = value       # inherited by the child processes
            cold = speed.cold(a.model, 256, "sky")
            run = drive(a.model, a.track, a.frames, dict(os.environ)) if a.track else float("nan")
            if rep:                                              # pass 0 warms the page cache and stamps
                rows[name]["cold"].append(cold)
                rows[name]["drive"].append(run)
            print(f"{'warm-up' if not rep else f'pass {rep}'}: stamps {name}: cold start {cold:.2f} s, "
                  f"drive {run:.1f} s", flush=True)
    for name, r in rows.items():
        print(f"stamps {name}: cold start {min(r['cold']):.2f}-{max(r['cold']):.2f} s, drive of {a.frames} frames "
              f"{min(r['drive']):.1f}-{max(r['drive']):.1f} s")


if __name__ == "__main__":
    main()
