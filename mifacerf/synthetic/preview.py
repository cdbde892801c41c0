"""Look at the synthetic subject: render a contact sheet of expressions to a PNG.

::

    python -m mifacerf.synthetic.preview                       # draft preset -> synthetic_subject.png
    python -m mifacerf.synthetic.preview --preset paper --res 160 --out /tmp/sheet.png
    python -m mifacerf.synthetic.preview --names smile,viseme_aa --view close

Rendering: Mitsuba perspective camera, ``path`` integrator with ``max_depth=2`` (direct light with
shadows, like the light stage), a dim constant environment plus a key and a fill directional light;
sRGB-encoded PNG with each tile labelled by the expression's name.
"""
from __future__ import annotations

import argparse

import numpy as np

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


def srgb8(img):
    img = np.clip(np.asarray(img, np.float64), 0.0, None)
    s = np.where(img <= 0.0031308, 12.92 * img, 1.055 * np.power(img, 1 / 2.4) - 0.055)
    return (np.clip(s, 0, 1) * 255 + 0.5).astype(np.uint8)


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
        im = Image.fromarray(srgb8(render_pose(scene, view, res, spp)))
        ImageDraw.Draw(im).text((4, 2), e.name, fill=(255, 255, 255))
        tiles.append(im)
    rows = (len(tiles) + cols - 1) // cols
    sheet = Image.new("RGB", (cols * res, rows * res), (40, 40, 40))
    for i, im in enumerate(tiles):
        sheet.paste(im, ((i % cols) * res, (i // cols) * res))
    sheet.save(path)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="draft", help="tiny | draft | paper")
    ap.add_argument("--names", default=None, help="comma-separated expression names (from the paper list)")
    ap.add_argument("--view", default="front", choices=sorted(VIEWS))
    ap.add_argument("--res", type=int, default=192)
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--cols", type=int, default=6)
    ap.add_argument("--out", default="synthetic_subject.png")
    a = ap.parse_args(argv)
    from .subject import default_subject

    subj = default_subject()
    ex = subj.presets(a.preset)
    if a.names:
        by = {e.name: e for e in subj.presets("paper")}
        ex = [by[n] for n in a.names.split(",")]
    print(contact_sheet(subj, ex, a.out, a.view, a.res, a.spp, a.cols))


if __name__ == "__main__":
    main()
