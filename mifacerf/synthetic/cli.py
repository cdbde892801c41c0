"""CLI: ``mifacerf synth`` (photograph a synthetic subject) and ``mifacerf truth`` (path-traced ground truth)."""
from __future__ import annotations

from pathlib import Path

import click

from ..execution import executor_options


@click.command("synth")
@click.argument("out", type=click.Path(file_okay=False))
@click.option("--preset", default="draft", show_default=True, type=click.Choice(["tiny", "draft", "paper"]),
              help="Rig size: tiny (tests, seconds), draft (demo, minutes), paper (480 lights, 60 expressions).")
@click.option("--subject", "subject_folder", type=click.Path(exists=True, file_okay=False), default=None,
              help="A folder with your own subject (neutral + expression meshes); default: the embedded head.")
@click.option("--scale", type=click.FloatRange(min=0, min_open=True), default=None,
              help="With --subject: file units to metres (0.01 for centimetres); overrides subject.json.")
@click.option("--dots", "n_dots", type=click.IntRange(min=1), default=None,
              help="With --subject: the number of fiducial dots on the visible skin (default 300).")
@click.option("--shapes", default=None, metavar="NAMES|GLOBS",
              help="With --subject: comma-separated expression meshes (names or globs, e.g. 'jaw*,mouthSmile_?') "
                   "that become controls; the preset's expressions are made from them.")
@click.option("--expressions", default=None, help="Comma-separated expression names (default: the preset's).")
@click.option("--overwrite", is_flag=True, help="Replace a complete capture already in OUT.")
@click.option("--contact-sheet/--no-contact-sheet", default=True, show_default=True,
              help="Also write OUT/contact_sheet.png.")
@click.option("--performance", type=click.FloatRange(min=0, min_open=True), default=None, metavar="SECONDS",
              help="Also record a multi-view performance this long into OUT/performance (an existing capture "
                   "is reused); see docs/tracking.md.")
@click.option("--performance-size", type=click.IntRange(min=1), default=192, show_default=True, help="Video resolution (square).")
@executor_options
def synth_cmd(out, preset, subject_folder, scale, n_dots, shapes, expressions, overwrite, contact_sheet, performance,
              performance_size, workers, cluster):
    """Render the light-stage capture of a synthetic subject into OUT/capture (truth: OUT/truth).

    The (expression, camera) takes are rendered by a local cluster (one worker process per core), the
    scheduler at --cluster, or this process alone with --workers 1 (docs/distributed.md)."""
    from ..execution import open_executor
    from ..formats.capture import CaptureError
    from .synth import synthesize

    given = [n for n, v in (("--scale", scale), ("--dots", n_dots), ("--shapes", shapes)) if v is not None]
    if given and subject_folder is None:
        raise click.UsageError(f"{', '.join(given)} only apply to a user's head (--subject FOLDER)")
    options = {"scale": scale, "n_dots": n_dots, "shapes": shapes.split(",") if shapes else None}
    reuse = performance is not None and not overwrite and (Path(out) / "capture" / "manifest.json").exists()
    try:
        seen = next(p for p in (Path(out), *Path(out).absolute().parents) if p.exists())   # OUT or its nearest parent
        with open_executor(workers if not reuse else 1, cluster, shared=[seen, subject_folder]) as executor:
            cap = Path(out) / "capture" if reuse else synthesize(
                out, preset, subject_folder, expressions.split(",") if expressions else None, overwrite,
                executor=executor, subject_options=options, report=lambda line: click.echo(f"subject: {line}"))
        if performance is not None:
            from .recording import record_performance

            click.echo(f"performance written to {record_performance(out, performance, size=performance_size)}")
    except (CaptureError, ValueError, OSError) as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(f"capture reused: {cap}" if reuse else f"capture written to {cap}")
    if contact_sheet and not reuse:
        from ..contact_sheet import contact_sheet as sheet

        png = sheet(cap, Path(out) / "contact_sheet.png")
        click.echo(f"contact sheet: {png}")


@click.command("truth")
@click.argument("out", type=click.Path(exists=True, file_okay=False))
@click.option("--expression", default="neutral", show_default=True,
              help="An expression name from OUT/truth/truth.json, or name=weight,... to blend parameter vectors.")
@click.option("--params", default=None, help="A parameter vector as control=value,... (overrides --expression).")
@click.option("--camera", default=None, help="A capture camera name (default: the second camera).")
@click.option("--yaw", type=float, default=None, help="Novel view: camera yaw in degrees (with --pitch).")
@click.option("--pitch", type=float, default=0.0, show_default=True)
@click.option("--env", "env", default="sky", show_default=True,
              help="Environment: sky, sunsky, interior, gradient, or a lat-long .exr/.hdr path.")
@click.option("--spp", type=click.IntRange(min=1), default=256, show_default=True)
@click.option("--size", type=click.IntRange(min=1), default=None, help="Image size (default: the capture camera's).")
@click.option("--dots/--no-dots", default=False, show_default=True,
              help="Show the fiducial dots (the model's renders are dot-free).")
@click.option("-o", "--output", default=None, help="Output .exr (a .png is written beside it).")
def truth_cmd(out, expression, params, camera, yaw, pitch, env, spp, size, dots, output):
    """Path-trace the synthetic subject of OUT (any expression, camera, environment) with alpha."""
    from ..imageio import write_exr, write_png
    from .truth_scene import TruthRenderer

    try:
        tr = TruthRenderer.from_synth(out, dots=dots)
    except (FileNotFoundError, ValueError) as exc:
        raise click.ClickException(str(exc)) from exc
    try:
        p = tr.params_from_spec(expression if params is None else params, is_params=params is not None)
        cam = tr.camera(camera, yaw, pitch, size)
        img = tr.render(p, cam, env, spp=spp)
    except (KeyError, ValueError) as exc:
        raise click.ClickException(str(exc)) from exc
    output = Path(output or Path(out) / "truth_renders" / f"{expression.replace('=', '-')}_{cam.name}_{Path(env).stem}.exr")
    output.parent.mkdir(parents=True, exist_ok=True)
    write_exr(output, img)
    write_png(output.with_suffix(".png"), img)
    click.echo(f"wrote {output} and {output.with_suffix('.png')}")
