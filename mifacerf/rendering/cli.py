"""CLI: ``mifacerf build`` (capture + registration → model) and ``mifacerf render``."""
from __future__ import annotations

from pathlib import Path

import click

from ..execution import executor_options
from .compression import DEFAULT_COMPRESS_METHOD, compressing_methods


@click.command("build")
@click.argument("capture", type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", required=True, type=click.Path(file_okay=False), help="The model folder to write.")
@click.option("--registration", type=click.Path(exists=True, file_okay=False), default=None,
              help="Registration folder (default: CAPTURE/registration).")
@click.option("--expressions", default=None, help="Comma-separated subset of registered expressions.")
@click.option("--no-culling", is_flag=True, help="Blend without §5.1 coherent culling.")
@click.option("--overwrite", is_flag=True,
              help="Replace an existing model in OUT (only once the new one is complete).")
@click.option("--allow-partial", is_flag=True,
              help="Build although the registration does not cover every expression of the capture.")
@executor_options
def build_cmd(capture, out, registration, expressions, no_culling, overwrite, allow_partial, workers, cluster):
    """Assemble the relightable morphable model from a registered capture.

    The model is written beside OUT and swapped in when complete: a failed or interrupted build leaves
    OUT as it was. Without --expressions, a registration that covers fewer expressions than the capture
    is an error unless --allow-partial."""
    from ..formats.capture import CaptureError
    from ..formats.registration import RegistrationError
    from .build import build_model
    from ..formats.model import ModelError

    inside = _inside(out, [capture] + ([registration] if registration else []))
    if inside:
        raise click.BadParameter(f"{out} is {'inside ' if Path(out).resolve() != Path(inside).resolve() else ''}"
                                 f"the input folder {inside}: the model goes in a folder of its own", param_hint="-o")
    from ..execution import open_executor

    try:
        with open_executor(workers, cluster, shared=[capture, registration]) as executor:   # a unit per field
            path = build_model(capture, out, registration, expressions.split(",") if expressions else None,
                               overwrite=overwrite, culling=not no_culling, allow_partial=allow_partial,
                               executor=executor)
    except (CaptureError, RegistrationError, ModelError, ValueError) as exc:
        raise click.ClickException(str(exc)) from exc
    click.echo(f"model written: {path.parent}")


def _inside(path, folders) -> str | None:
    """The first of ``folders`` that ``path`` is, or lies inside (after resolving links), else None."""
    p = Path(path).resolve()
    for f in folders:
        if p == Path(f).resolve() or Path(f).resolve() in p.parents:
            return str(f)
    return None


@click.command("render")
@click.argument("scene_or_model", type=click.Path(exists=True))
@click.option("-o", "--output", default="render.exr", show_default=True)
@click.option("-D", "defines", multiple=True, help="Scene parameter, NAME=VALUE (scene files).")
@click.option("--spp", type=click.IntRange(min=1), default=None, help="Samples per pixel (default: the scene's sampler).")
@click.option("-t", "--threads", type=click.IntRange(min=1), default=None, help="CPU threads (default: all).")
def render_cmd(scene_or_model, output, defines, spp, threads):
    """Render a scene file (scenes/*.xml) that uses mifacerf's plugins."""
    from ..formats.files import replacing
    from .scenefile import render_scene_file

    if Path(scene_or_model).is_dir():
        kind = "a model folder" if (Path(scene_or_model) / "model.json").exists() else "a folder"
        raise click.BadParameter(f"{scene_or_model} is {kind}, not a scene file; render a model through a scene: "
                                 f"mifacerf render scenes/face_envmap.xml -D model={scene_or_model}",
                                 param_hint="SCENE_OR_MODEL")
    bad = [d for d in defines if "=" not in d]
    if bad:
        raise click.BadParameter(f"expected NAME=VALUE, got {bad[0]!r}", param_hint="-D")
    # the EXR and its PNG replace the old pair as one transaction (formats.files.replacing): one render at
    # a time per OUTPUT (a second is refused, exit 3); a failed, killed or out-of-space render leaves the
    # previous pair, and one killed between its two renames is completed by the next render to OUTPUT
    try:
        with replacing(output, (".png",), ValueError, what="render to this output (mifacerf render -o)") as tmp:
            render_scene_file(scene_or_model, tmp, dict(d.split("=", 1) for d in defines), spp=spp, threads=threads)
    except (KeyError, ValueError, FileNotFoundError, RuntimeError) as exc:
        if isinstance(exc, OSError) and exc.errno is not None:
            raise                         # an I/O error: '<file>: <reason>' from the top of the command
        raise click.ClickException(str(exc.args[0]) if exc.args else str(exc)) from exc
    click.echo(f"wrote {output}")


@click.command("compress")
@click.argument("model", type=click.Path(exists=True, file_okay=False))
@click.option("--method", type=click.Choice(compressing_methods()), default=DEFAULT_COMPRESS_METHOD, show_default=True,
              help="Compression method (mifacerf.rendering.compression.COMPRESSION_METHODS).")
@click.option("--rank", type=click.IntRange(min=1), multiple=True, default=(8,), show_default=True,
              help="Coefficients per texel (repeat for several).")
@executor_options
def compress_cmd(model, method, rank, workers, cluster):
    """Add PCA-compressed versions of every reflectance field to a model.

    The fields are compressed by a local cluster (one worker process per core), the scheduler at --cluster,
    or this process alone with --workers 1; this process writes them (docs/distributed.md)."""
    from ..execution import open_executor
    from .compression import compress_model
    from .model import Model

    m = Model(model)
    with open_executor(workers, cluster, shared=[model]) as executor:
        info = compress_model(m, list(rank), method=method, executor=executor)
    sizes = info["bytes"] if isinstance(info["bytes"], dict) else {rank[0]: info["bytes"]}
    for k, b in sizes.items():
        click.echo(f"rank {k}: {info['fields']} fields, {b / 1e6:.1f} MB")
