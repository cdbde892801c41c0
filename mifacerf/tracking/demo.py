"""The performance stage of ``mifacerf demo``: record (once), track, drive — within the demo's time budget.

``run_performance(OUT, MODEL)``:

1. records a 2 s performance into ``OUT/performance`` (192 px, six cameras, 60 fps), reusing the
   capture's rig and template — skipped when it is already there;
2. tracks it with the model as rest reference (``OUT/performance/track``);
3. drives the model with it under the ``interior`` environment from the second capture camera,
   composited into the plate: ``OUT/performance_render/interior/{frames/, performance.mp4}``.

The comparison of the track with the truth is the demo's (:func:`mifacerf.demo.stage_performance`,
through :mod:`mifacerf.evaluation.tracking`). Path-traced ground truth for every frame is left to
``mifacerf evaluate drive`` (docs/tracking.md): at 64 samples per pixel it costs ~3 s a frame on two cores.
"""
from __future__ import annotations

from pathlib import Path

SECONDS = 2.0
SIZE = 192
ENV = "interior"


def run_performance(out, model, seconds: float = SECONDS, size: int = SIZE, env: str = ENV) -> dict:
    """Record (if needed), track and drive; returns the stage's metrics (JSON-able; ``track``: the track folder)."""
    import click

    from .drive import drive
    from ..synthetic.recording import record_performance
    from .track import Track, track_performance

    out = Path(out)
    perf = out / "performance"
    if (perf / "manifest.json").exists():
        click.echo(f"   cached: {perf}")
    else:
        record_performance(out, seconds, size=size, log=click.echo)
    track = Track(track_performance(perf, perf / "track", model=model, log=click.echo))
    d = drive(track, model, out / "performance_render", envs=(env,), log=click.echo)
    import json

    meta = json.loads((d / "drive.json").read_text())
    e = meta["environments"][env]
    return {
        "frames": track.n_frames, "fps": track.fps, "track": str(track.root),
        "tracking_seconds_per_frame": track.meta["time_s"]["per_frame_mean"],
        "render_seconds_per_frame": e["render_seconds_per_frame"],
        "weights_coherence": meta["weights"]["coherence"], "pixel_coherence": e["pixel_coherence"],
        "video": str(d / e["video"]),
    }
