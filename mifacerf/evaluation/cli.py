"""CLI: ``mifacerf bench`` (run time against error) and ``mifacerf evaluate …``: the comparisons with the
synthetic ground truth, one sub-command per stage — ``render`` (:mod:`.render_cases`), ``registration``
(:mod:`.registration`), ``tracking`` (:mod:`.tracking`), ``drive`` (:mod:`.drive`), ``blending``
(:mod:`.blending`) — and ``blending-speed`` (:mod:`mifacerf.blending.benchmark`).

Imports sit inside the commands so that ``mifacerf evaluate --help`` stays fast.
"""
from __future__ import annotations

import json
from pathlib import Path

import click

from ..execution import executor_options
from ..tracking.cli import drive_options


@click.command("bench")
@click.argument("model", type=click.Path(exists=True, file_okay=False))
@click.option("--synth", "synth_out", required=True, type=click.Path(exists=True, file_okay=False),
              help="The synth output the model was built from (its ground truth is the error reference).")
@click.option("-o", "--out", default="bench", show_default=True, type=click.Path(file_okay=False))
@click.option("--frames", "n_frames", type=click.IntRange(min=1), default=3, show_default=True)
@click.option("--size", type=click.IntRange(min=1), default=256, show_default=True)
@click.option("--env", default="sky", show_default=True)
@click.option("--spp-truth", type=click.IntRange(min=1), default=1024, show_default=True)
@click.option("--quick", is_flag=True, help="Only dense, exact and the first compressed rank.")
@executor_options
def bench_cmd(model, synth_out, out, n_frames, size, env, spp_truth, quick, workers, cluster):
    """Benchmark run time per frame against error: dense reference, exact path, compressed ranks.

    The ground truths and the configurations are units on the scheduler at --cluster or a local cluster of
    --workers processes; by default (neither given, nor MIFACERF_WORKERS / MIFACERF_CLUSTER) this process
    alone, since configurations that run at once on one machine share its cores and time each other's load
    (docs/distributed.md)."""
    import os

    from ..execution import CLUSTER_ENV, WORKERS_ENV, open_executor
    from .bench import run

    if workers is None and not cluster and not os.environ.get(WORKERS_ENV) and not os.environ.get(CLUSTER_ENV):
        workers = 1
    Path(out).mkdir(parents=True, exist_ok=True)
    with open_executor(workers, cluster, shared=[model, synth_out, out]) as executor:
        report = run(model, synth_out, out, n_frames=n_frames, size=size, env=env, spp_truth=spp_truth, quick=quick,
                     executor=executor)
    click.echo((Path(out) / "table.md").read_text())
    click.echo(f"plot: {Path(out) / 'runtime_vs_error.png'}")
    del report


@click.group("evaluate", context_settings={"help_option_names": ["-h", "--help"]})
def evaluate_group():
    """Compare a stage's output with the synthetic ground truth (evaluation only: no stage reads the truth).

    OUT is a 'mifacerf synth' output folder (capture/ and truth/). Also here: blending-speed, the timing of
    the blend weights against their NumPy reference.
    """


@evaluate_group.command("render", short_help="Rendering accuracy against path-traced truth.")
@click.argument("synth_out", metavar="OUT", type=click.Path(exists=True, file_okay=False))
@click.argument("model", type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", default="evaluation", show_default=True, type=click.Path(file_okay=False))
@click.option("--envs", default="sky,interior,gradient", show_default=True)
@click.option("-n", "n", type=click.IntRange(min=1), default=2, show_default=True, help="Cases per kind (a, b, c, d).")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Default: a fresh seed from the clock (recorded).")
@click.option("--spp-truth", type=click.IntRange(min=1), default=1024, show_default=True)
@click.option("--size", type=click.IntRange(min=1), default=None, help="Frame size in pixels (default: the cameras' own).")
@executor_options
def render_cmd(synth_out, model, out, envs, n, seed, spp_truth, size, workers, cluster):
    """Rendering accuracy of MODEL against path-traced ground truth: captured, blends, novel views, out-of-set."""
    import time

    from ..execution import open_executor
    from .render_cases import evaluate

    seed = int(time.time()) if seed is None else seed
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with open_executor(workers, cluster, shared=[synth_out, model]) as executor:   # a unit per case and env
        report = evaluate(synth_out, model, envs=tuple(envs.split(",")), n=n, seed=seed, spp_truth=spp_truth,
                          size=size, pictures=out / "cases.png", executor=executor)
    (out / "report.json").write_text(json.dumps(report, indent=1))
    for e in report["cases"]:
        click.echo(f"  {e['label'][:48]:48s} {e['env']:9s} face {e['psnr']:.2f} dB, "
                   f"composite {e['psnr_composite']:.2f} dB, IoU {e['silhouette_iou']:.4f}, "
                   f"uncovered {100 * e['uncovered']:.2f} %")
    for k, v in report["summary"].items():
        mean = lambda m: v[m].get("mean", float("nan"))  # noqa: E731
        click.echo(f"case {k}: PSNR {mean('psnr'):.2f} dB (min {v['psnr'].get('min', 0):.2f}; "
                   f"truth noise subtracted {mean('psnr_noise_corrected'):.2f}), "
                   f"composite {mean('psnr_composite'):.2f} dB (min {v['psnr_composite'].get('min', 0):.2f}), "
                   f"IoU {mean('silhouette_iou'):.4f} (min {v['silhouette_iou'].get('min', 0):.4f}), "
                   f"uncovered {100 * mean('uncovered'):.2f} % (max {100 * v['uncovered'].get('max', 0):.2f} %), "
                   f"{mean('seconds'):.2f} s/frame")
        if "error_share" in v:
            click.echo("        composite error: " + ", ".join(
                f"{r} {100 * s.get('mean', 0):.0f} %" for r, s in v["error_share"].items()))
    click.echo(f"truth noise floor: {report['truth_noise_psnr']:.1f} dB (lowest case); report: {out / 'report.json'}")


@evaluate_group.command("registration", short_help="A registration against the true fiducials.")
@click.argument("synth_out", metavar="OUT", type=click.Path(exists=True, file_okay=False))
@click.option("--registration", default=None, type=click.Path(file_okay=False),
              help="The registration folder to evaluate (default: OUT/capture/registration).")
@click.option("--json", "json_path", default=None, type=click.Path(dir_okay=False), help="Write the full result here.")
@click.option("--pictures", default=None, help="Write PNGs of these expressions (comma-separated) ...")
@click.option("--pictures-dir", default="registration-pictures", show_default=True, type=click.Path(file_okay=False),
              help="... into this folder.")
def registration_cmd(synth_out, registration, json_path, pictures, pictures_dir):
    """A registration of OUT's capture against the truth: fiducials, dot removal, lips and lids, head, teeth,
    eyes (a Markdown table)."""
    from . import registration as R

    out = Path(synth_out)
    res = R.evaluate(out / "capture", out / "truth", registration)
    click.echo(R.format_table(res))
    if json_path:
        Path(json_path).write_text(json.dumps(res, indent=1))
    for name in (pictures.split(",") if pictures else []):
        for path in R.pictures(out / "capture", out / "truth", registration, pictures_dir, name.strip()):
            click.echo(path)


@evaluate_group.command("blending", short_help="The §5 weights against true deformations.")
@click.option("--subject", type=click.Choice(["synthetic", "toy"]), default="synthetic", show_default=True)
@click.option("--residual-threshold", type=click.FloatRange(min=0), default=None, help="Default: the model's.")
@click.option("--similarity-threshold", type=click.FloatRange(min=0), default=None, help="Default: the model's.")
@click.option("--out", "out_dir", default=None, type=click.Path(file_okay=False), help="Folder for the pictures.")
@click.option("--json", "json_path", default=None, type=click.Path(dir_okay=False), help="Write the numbers here.")
def blending_cmd(subject, residual_threshold, similarity_threshold, out_dir, json_path):
    """The §5 weights against true deformations: local-deformation error with and without culling."""
    import os

    from . import blending as B

    if subject == "synthetic":
        try:
            problem = B.synthetic_problem()
        except (ImportError, AttributeError, ModuleNotFoundError) as exc:
            raise click.ClickException(f"the synthetic subject is not available ({exc}); use --subject toy") from exc
    else:
        problem = B.toy_problem()
    out = B.run(problem, residual_threshold, similarity_threshold, out_dir=out_dir)
    if out_dir:
        B.dims_picture(problem, (5e-5, 2e-4, 5e-4), os.path.join(out_dir, "blending_dims_thresholds.png"))
    click.echo(json.dumps(out, indent=1))
    if json_path:
        with open(json_path, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=1)


@evaluate_group.command("blending-speed", short_help="Time the §5 weights: Dr.Jit against the reference.")
@click.option("--vertices", type=click.IntRange(min=1), default=300, show_default=True)
@click.option("--sources", type=click.IntRange(min=1), default=60, show_default=True)
@click.option("--frames", type=click.IntRange(min=1), default=10000, show_default=True)
@click.option("--threads", type=click.IntRange(min=1), default=None, help="Dr.Jit worker threads (default: all cores).")
@click.option("--json", "json_path", default=None, type=click.Path(dir_okay=False), help="Also write the numbers here.")
def blending_speed_cmd(vertices, sources, frames, threads, json_path):
    """Time the §5 weights: the Dr.Jit evaluator against the NumPy/SciPy reference (toy sheet)."""
    from ..blending.benchmark import run

    out = run(vertices, sources, frames, threads=threads)
    if json_path:
        with open(json_path, "w", encoding="utf-8") as f:
            json.dump(out, f, indent=1)


@evaluate_group.command("tracking", short_help="A track against the true performance.")
@click.argument("synth_out", metavar="OUT", type=click.Path(exists=True, file_okay=False))
@click.argument("track", required=False, type=click.Path(exists=True, file_okay=False))
@click.option("--overlay", "overlays", multiple=True, type=click.IntRange(min=0),
              help="Also write TRACK/overlay_F<frame>_<camera>.png for this frame: the tracked dots and, as blue "
                   "crosses, the true ones.")
def tracking_cmd(synth_out, track, overlays):
    """A TRACK of OUT's performance against OUT/truth/performance: dots, head pose, gaze, lips and lids
    (TRACK/evaluation.json; TRACK defaults to OUT/performance/track)."""
    from ..tracking.track import Track
    from .tracking import evaluate_track, overlay

    tr = Track(track or Path(synth_out) / "performance" / "track")
    for f in overlays:
        for cam in tr.meta["cameras"]:
            overlay(tr, min(f, tr.n_frames - 1), cam, tr.root / f"overlay_F{f:05d}_{cam}.png", truth=synth_out)
        click.echo(f"overlays of frame {f}: {tr.root}/overlay_F{f:05d}_*.png")
    e = evaluate_track(tr, synth_out)
    click.echo(f"dot error (tracked dots): median {e['dot_error']['median']} px, 95th percentile "
               f"{e['dot_error']['p95']} px; dots tracked through the whole sequence: "
               f"{100 * e['dots_tracked_whole_sequence']:.1f} %  ({tr.root / 'evaluation.json'})")


@evaluate_group.command("drive", short_help="Driven renders against path-traced truth.")
@click.argument("synth_out", metavar="OUT", type=click.Path(exists=True, file_okay=False))
@click.argument("track", type=click.Path(exists=True, file_okay=False))
@drive_options
@click.option("--truth-spp", type=click.IntRange(min=1), default=64, show_default=True, help="Samples per pixel of the truth.")
def drive_cmd(synth_out, track, truth_spp, **options):
    """'mifacerf drive TRACK' with every frame path-traced from OUT's true performance: PSNR per frame,
    the truth's noise floor and coherence (in drive.json), truth above render in strip.png."""
    from ..tracking.cli import run_drive
    from .drive import evaluate_drive

    def drive(track, model, out, **keywords):
        return evaluate_drive(track, model, synth_out, out, truth_spp=truth_spp, **keywords)

    run_drive(drive, track, **options)


@evaluate_group.command("material", short_help="The material under Mitsuba's integrators against the exact path.")
@click.argument("model", type=click.Path(exists=True, file_okay=False))
@click.option("--env", default="sky", show_default=True, help="A generated environment name or a lat-long file.")
@click.option("--size", type=click.IntRange(min=1), default=48, show_default=True)
@click.option("--spp", type=click.IntRange(min=1), default=256, show_default=True, help="Samples per pixel of each material pass.")
@click.option("--integrators", default="direct,path", show_default=True)
@click.option("--no-self-visibility", is_flag=True, help="Keep the captured self-shadowing in the material.")
@click.option("--eye", default="0.12,0.1,1.0", show_default=True,
              help="X,Y,Z: the camera's position in metres, looking at the origin.")
@click.option("--visibility-grid", type=click.IntRange(min=0), default=None,
              help="facerf_bsdf visibility_grid: the self-visibility grid order inside each triangle (default 3).")
@click.option("--near-occluders", type=click.FloatRange(min=0), default=None,
              help="facerf_bsdf near_occluders (metres), for --integrators facerf_direct.")
@click.option("--visibility-emitter", is_flag=True,
              help="facerf_bsdf visibility_emitter: the cell shares weighted by the scene's environment.")
def material_cmd(model, env, size, spp, integrators, no_self_visibility, eye, visibility_grid, near_occluders,
                 visibility_emitter):
    """The material under Mitsuba's integrators against the exact path: facerf_bsdf rendered by each
    integrator (two passes) against the facerf integrator under ENV; PSNR, noise floor, brightness ratio."""
    from .material import compare, format_rows, material_options, parse_eye

    try:
        at = parse_eye(eye)
    except ValueError as e:
        raise click.BadParameter(str(e), param_hint="'--eye'") from None
    bsdf = material_options(not no_self_visibility, None, visibility_grid, near_occluders, visibility_emitter)
    click.echo(format_rows(compare(model, env, integrators.split(","), size, spp, bsdf=bsdf, eye=at)))
