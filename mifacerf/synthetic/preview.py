"""Look at the synthetic subject: render a contact sheet of expressions to a PNG.

::

    mifacerf preview                                    # draft preset -> synthetic_subject.png
    mifacerf preview --preset paper --res 160 --out /tmp/sheet.png
    mifacerf preview --names smile,viseme_aa --view close

Rendering: Mitsuba perspective camera, ``path`` integrator with ``max_depth=2`` (direct light with
shadows, like the light stage), a dim constant environment plus a key and a fill directional light;
sRGB-encoded PNG with each tile labelled by the expression's name.
"""
from __future__ import annotations

import click
import numpy as np

from ..imageio import to_srgb8
from ..variant import ensure_variant

VIEWS = {
    "front": ([0.0, -0.01, 0.75], [0.0, -0.03, 0.0], 24.0),
    "three_quarter": ([0.48, 0.0, 0.58], [0.0, -0.03, 0.0], 24.0),
    "profile": ([0.75, 0.0, 0.0], [0.0, -0.03, 0.0], 24.0),
    "close": ([0.0, 0.0, 0.5], [0.0, -0.02, 0.05], 17.0),
}
LIGHTS = {
    "env": {"type": "constant", "radiance": {"type": "rgb", "value": 0.12}},
    "key": {"type": "directional", "direction": [-0.35, -0.55, -1.0], "irradiance": {"type": "rgb", "value": 2.4}},
    "fill": {"type": "directional", "direction": [0.8, -0.1, -0.6], "irradiance": {"type": "rgb", "value": 0.7}},
}


def render_pose(scene, view="front", res=192, spp=32, seed=0):
    """Linear RGB (res, res, 3) of a :class:`SubjectScene` (which should hold :data:`LIGHTS`)."""
    mi = ensure_variant()
    eye, target, fov = VIEWS[view] if isinstance(view, str) else view
    sensor = mi.load_dict({
        "type": "perspective", "fov": fov,
        "to_world": mi.ScalarTransform4f().look_at(origin=eye, target=target, up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "gaussian"}},
        "sampler": {"type": "independent", "sample_count": spp}})
    integ = mi.load_dict({"type": "path", "max_depth": 2})
    return np.array(mi.render(scene.scene, sensor=sensor, integrator=integ, seed=seed))[..., :3]


def contact_sheet(subject, expressions, path, view="front", res=192, spp=32, cols=6):
    """Render ``expressions`` (Expression objects) into a labelled grid PNG at ``path``."""
    from PIL import Image, ImageDraw

    from .scene import SubjectScene

    scene = SubjectScene(subject, extra=LIGHTS)
    tiles = []
    for e in expressions:
        scene.set_pose(subject.pose(e.params))
        im = Image.fromarray(to_srgb8(render_pose(scene, view, res, spp)))
        ImageDraw.Draw(im).text((4, 2), e.name, fill=(255, 255, 255))
        tiles.append(im)
    rows = (len(tiles) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * res, rows * res), (40, 40, 40))
    for i, im in enumerate(tiles):
        sheet.paste(im, ((i % cols) * res, (i // cols) * res))
    sheet.save(path)
    return path


@click.command("preview")
@click.option("--preset", default="draft", show_default=True, help="tiny | draft | paper")
@click.option("--names", default=None, help="Comma-separated expression names (from the paper list).")
@click.option("--view", default="front", show_default=True, type=click.Choice(sorted(VIEWS)))
@click.option("--res", type=click.IntRange(min=1), default=192, show_default=True)
@click.option("--spp", type=click.IntRange(min=1), default=32, show_default=True)
@click.option("--cols", type=click.IntRange(min=1), default=6, show_default=True)
@click.option("--out", default="synthetic_subject.png", show_default=True, type=click.Path(dir_okay=False))
def preview_cmd(preset, names, view, res, spp, cols, out):
    """Look at the synthetic subject: a contact sheet of its expressions (no capture needed)."""
    from .subject import default_subject

    subj = default_subject()
    ex = subj.presets(preset)
    if names:
        by = {e.name: e for e in subj.presets("paper")}
        ex = [by[n] for n in names.split(",")]
    click.echo(contact_sheet(subj, ex, out, view, res, spp, cols))
