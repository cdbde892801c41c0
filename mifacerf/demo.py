"""``mifacerf demo``: the main job on the embedded synthetic subject."""
from __future__ import annotations

from pathlib import Path

import click


@click.command("demo")
@click.option("-o", "--out", default="mifacerf-demo", show_default=True, type=click.Path(file_okay=False),
              help="Output folder (the synthetic capture is cached inside it).")
@click.option("--preset", default="draft", show_default=True, type=click.Choice(["tiny", "draft", "paper"]))
def demo_cmd(out, preset):
    """Synthesise the default subject (cached) and write its contact sheet."""
    from tqdm.auto import tqdm

    from .contact_sheet import contact_sheet
    from .synthetic.synth import synthesize

    out = Path(out)
    cap = out / "capture"
    if not (cap / "manifest.json").exists():
        synthesize(out, preset)
    else:
        click.echo(f"using the cached capture in {cap}")
    png = contact_sheet(cap, out / "contact_sheet.png", progress=lambda x: tqdm(x, desc="contact sheet"))
    click.echo(f"contact sheet: {png}")
