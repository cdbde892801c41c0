"""Give an existing synthetic capture a template with (or without) extensions (issue 16).

    python scripts/template_extensions.py CAPTURE [--neck-cut -0.216] [--spacing 0.014] [--no-extensions]

Rewrites ``CAPTURE/hand/template.json`` from the procedural subject's template
(:func:`mifacerf.synthetic.template.build_template` with the options given) keeping everything the
synthetic user placed in the existing file — every face vertex, the teeth strips, the eyes — so the face's
registration inputs are unchanged and the coarse points and rotoscoping stay valid; the extension vertices
(scalp, ears, sides, neck down to the cut) are placed on the neutral's truth with ~1 px clicking error
(:func:`mifacerf.synthetic.hand_inputs.rewrite_template`). Then register again (``mifacerf register
CAPTURE --force``: the registration's template changed) and build — or, with ``--extend REGISTRATION``,
keep that registration's face and only place the extensions in each of its expressions
(:func:`mifacerf.registration.extend.extend_registration`, written to ``CAPTURE/registration-extended``;
build with ``--registration CAPTURE/registration-extended``). The rendering evaluation draws its
targets from the same subject template, so evaluate with the default options (or the same ones).

Only for captures synthesised from the procedural subject (``mifacerf synth``); a real user edits
``template.json`` (docs/registration.md, "Extensions").
"""
from __future__ import annotations

import click


@click.command()
@click.argument("capture", type=click.Path(exists=True, file_okay=False))
@click.option("--neck-cut", type=float, default=None, help="Height of the neck's cut (m, head frame; default -0.216).")
@click.option("--spacing", type=click.FloatRange(min=0.004), default=None,
              help="Sample spacing of the extension mesh (m; default 0.014).")
@click.option("--no-extensions", is_flag=True, help="Write the face template alone (as before issue 16).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True, help="Clicking-noise seed.")
@click.option("--extend", "extend", type=click.Path(exists=True, file_okay=False), default=None,
              help="A registration of CAPTURE on the face template: keep it, place the extensions in it.")
def main(capture, neck_cut, spacing, no_extensions, seed, extend):
    from mifacerf.formats.capture import Capture
    from mifacerf.synthetic.hand_inputs import rewrite_template
    from mifacerf.synthetic.subject import default_subject
    from mifacerf.synthetic.template import build_template

    cap = Capture(capture)
    subject = default_subject()
    options = {k: v for k, v in (("neck_cut_y", neck_cut), ("spacing", spacing)) if v is not None}
    subject.template = build_template(subject, extensions=not no_extensions, **options)
    path = rewrite_template(capture, subject, cap.rig, seed=seed)
    n_ext = sum(len(e["vertices"]) for e in subject.template.extensions.values())
    click.echo(f"{path}: {subject.template.n_vertices} vertices ({n_ext} in {len(subject.template.extensions)} "
               f"extensions), {len(subject.template.triangles)} triangles")
    if extend:
        from mifacerf.registration.extend import extend_registration

        out = extend_registration(capture, extend, log=click.echo)
        click.echo(f"registration with extensions: {out}")


if __name__ == "__main__":
    main()
