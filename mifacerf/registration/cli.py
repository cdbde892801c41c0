"""``mifacerf register CAPTURE``: register a light-stage capture (paper §3–4). Heavy imports stay inside."""
from __future__ import annotations

import click

from .dot_removal import DEFAULT_DOT_FILL_METHOD, DOT_FILL_METHODS


@click.command("register")
@click.argument("capture", type=click.Path(exists=True, file_okay=False))
@click.option("--out", type=click.Path(file_okay=False), default=None,
              help="Registration folder (default: CAPTURE/registration).")
@click.option("--expressions", default=None, help="Comma-separated expressions to register (default: all; "
              "the neutral is always registered first).")
@click.option("--force", is_flag=True, help="Register again expressions already registered.")
@click.option("--no-dot-removal", is_flag=True, help="Skip removing the dots from the OLAT images.")
@click.option("--dot-fill", type=click.Choice(list(DOT_FILL_METHODS)), default=DEFAULT_DOT_FILL_METHOD, show_default=True,
              help="How dots are filled: texture-aware with each light's share kept, or harmonic (smooth).")
@click.option("--radius-px", type=click.FloatRange(min=0, min_open=True), default=None, help="3-D search radius of the snap, in pixel footprints.")
@click.option("--floor", type=click.FloatRange(0, 1, min_open=True), default=None,
              help="Lowest dot-strength threshold, as a fraction of the initial one.")
@click.option("--curved", type=click.IntRange(min=1), default=None,
              help="The surface renders trace and the extensions' outlines are fitted against: the template's "
                   "Phong surface split this many times per edge; 1: its flat triangles (default: 3).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def register_cmd(capture, out, expressions, force, no_dot_removal, dot_fill, radius_px, floor, curved, quiet):
    """Register every expression of CAPTURE into the template (reads only CAPTURE: manifest, images, hand/).

    Writes per expression the registered mesh, texture coordinates, visibility, head pose, teeth and
    eye placement, dot-free image patches and a report (docs/registration.md). Expressions already
    registered are skipped unless --force.
    """
    import json
    from pathlib import Path

    from ..formats.capture import CaptureError
    from .register import Options, RegistrationInputError, register_capture

    opt = Options(remove_dots=not no_dot_removal, dot_fill=dot_fill)
    if radius_px is not None:
        opt.radius_px = radius_px
    if floor is not None:
        opt.floor = floor
    if curved is not None:
        opt.curved = curved
    names = [n.strip() for n in expressions.split(",") if n.strip()] if expressions else None
    try:
        folder = register_capture(capture, out=out, expressions=names, force=force, options=opt,
                                  progress=not quiet)
    except (RegistrationInputError, CaptureError) as exc:
        raise click.ClickException(str(exc)) from exc
    meta = json.loads((Path(folder) / "registration.json").read_text())
    click.echo(f"registration written to {folder}")
    for problem in meta.get("hand_input_problems", []):
        click.echo(f"  hand input: {problem}")
    for name, rep in meta.get("expressions", {}).items():
        if names and name not in names:
            continue
        dr = rep.get("dot_removal") or {}
        line = (f"  {name:<20} {100 * rep['registered_fraction']:5.1f}% of {rep['n_dots']} fiducials registered")
        if dr:
            line += f"; dot response {dr['response_before']:.3f} -> {dr['response_after']:.3f}"
        click.echo(line)
        for flag in rep.get("flags", []):
            click.echo(f"      ! {flag}")
