"""CLI: ``mifacerf track`` (performance → per-frame target mesh) and ``mifacerf drive`` (track → relit video).

The performance itself is recorded by ``mifacerf synth OUT --performance SECONDS``; the comparisons with
the synthetic truth are ``mifacerf evaluate tracking`` and ``mifacerf evaluate drive``
(:mod:`mifacerf.evaluation.cli`, which shares the drive options below).
"""
from __future__ import annotations

from pathlib import Path

import click

from ..execution import executor_options


@click.command("track")
@click.argument("performance", type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", default=None, type=click.Path(file_okay=False),
              help="Track folder to write (default: PERFORMANCE/track).")
@click.option("--model", default=None, type=click.Path(exists=True, file_okay=False),
              help="A model built from the same subject: its registered neutral is the rest reference and it "
                   "knows the eyeball centres (default: the performance's template).")
@click.option("--frames", type=click.IntRange(min=1), default=None, help="Track only the first N frames.")
@click.option("--smooth", type=click.FloatRange(min=0), default=1.0, show_default=True,
              help="Temporal smoothing of tracked dots (Gaussian sigma, frames; 0 = off).")
@click.option("--overlay", "overlays", multiple=True, type=click.IntRange(min=0),
              help="Also write TRACK/overlay_F<frame>_<camera>.png (tracked dots over the video) for this frame.")
def track_cmd(performance, out, model, frames, smooth, overlays):
    """Track the dots of a multi-view PERFORMANCE; write the per-frame target mesh (paper §6.4)."""
    from ..formats.performance import PerformanceError
    from .track import TrackError, track_performance
    from .track3d import Options

    try:
        path = track_performance(performance, out, model=model, options=Options(smooth_sigma=smooth),
                                 frames=frames, log=click.echo)
    except (PerformanceError, TrackError, OSError) as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(f"track written to {path}")
    from .overlay import overlay
    from .track import Track

    tr = Track(path)
    for f in overlays:
        for cam in tr.meta["cameras"]:
            overlay(tr, min(f, tr.n_frames - 1), cam, path / f"overlay_F{f:05d}_{cam}.png")
        click.echo(f"overlays of frame {f}: {path}/overlay_F{f:05d}_*.png")


#: the options of ``mifacerf drive`` (``mifacerf evaluate drive`` takes them too): see :func:`drive_options`
DRIVE_OPTIONS = (
    click.option("--model", required=True, type=click.Path(exists=True, file_okay=False), help="The model to drive."),
    click.option("-o", "--out", default=None, type=click.Path(file_okay=False), help="Default: TRACK/drive."),
    click.option("--env", "envs", multiple=True, default=("sky", "interior"), show_default=True,
                 help="Environment(s): sky, sunsky, interior, gradient or a lat-long .exr/.hdr (repeat)."),
    click.option("--camera", default=None,
                 help="A capture camera's name, or yaw,pitch in degrees (default: the model's second camera)."),
    click.option("--size", type=click.IntRange(min=1), default=None, help="Image size (square; default: the camera's)."),
    click.option("--spp", type=click.IntRange(min=1), default=4, show_default=True),
    click.option("--frames", default=None, help="Drive only the first N frames, or frames A:B[:STEP] (B excluded)."),
    click.option("--no-exr", is_flag=True, help="Write the PNG frames and the video only."),
    click.option("--weight-smoothing", type=click.FloatRange(min=0), default=2.0, show_default=True,
                 help="Temporal filter of the §5 weights (Gaussian sigma in frames; 0 = off)."),
    click.option("--method", default="exact", show_default=True,
                 help="How the fields are lit: exact, or a compressed copy the model holds (sh, pca: with --rank)."),
    click.option("--rank", type=click.IntRange(min=1), default=None,
                 help="The compressed copy's rank / order (mifacerf compress --rank)."),
)


def drive_options(command):
    """Decorate a click command with :data:`DRIVE_OPTIONS` (its function takes them as keywords)."""
    for option in reversed(DRIVE_OPTIONS):
        command = option(command)
    return command


def run_drive(drive, track, model, out, envs, camera, size, spp, frames, no_exr, weight_smoothing, method="exact",
              rank=None) -> Path:
    """Parse :data:`DRIVE_OPTIONS` and call ``drive(track, model, out, **keywords)`` (:func:`.drive.drive` or
    one with the same keywords); errors become click errors, the result is echoed."""
    from ..formats.model import ModelError
    from .track import TrackError

    if frames is not None:
        try:
            frames = tuple(int(x) for x in frames.split(":")) if ":" in frames else int(frames)
        except ValueError:
            raise click.BadParameter(f"expected N or A:B[:STEP], got {frames!r}", param_hint="--frames") from None
    cam = camera
    if camera and "," in camera:
        cam = tuple(float(x) for x in camera.split(","))
    try:
        path = drive(track, model, out, envs=envs, camera=cam, size=size, spp=spp, frames=frames, exr=not no_exr,
                     weight_sigma=weight_smoothing, log=click.echo, method=method, rank=rank)
    except (TrackError, ModelError, ValueError, KeyError, OSError) as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(f"driven performance written to {path} (videos: {', '.join(str(p) for p in sorted(Path(path).glob('*/performance.mp4')))})")
    return path


@click.command("drive")
@click.argument("track", type=click.Path(exists=True, file_okay=False))
@drive_options
@executor_options
def drive_cmd(track, workers, cluster, **options):
    """Drive MODEL with a TRACK: §5 weights per frame, relit renders, composites, a video (paper §7).

    The frames are rendered by a local cluster (one worker process per core), the scheduler at --cluster,
    or this process alone with --workers 1; the files written are the same (docs/distributed.md)."""
    from functools import partial

    from ..execution import open_executor
    from .drive import drive

    with open_executor(workers, cluster, shared=[options["model"]]) as executor:
        run_drive(partial(drive, executor=executor), track, **options)
