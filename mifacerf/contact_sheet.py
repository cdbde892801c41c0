"""Contact sheet of a capture: every expression seen by one camera, under one light and relit.

Works on any capture folder (it reads only the capture): per expression, the OLAT
image of the light closest to the camera's upper left (a portrait key light) and the
plain weighted sum of all OLAT images under a generated environment (each weight =
the environment integrated over that light's spherical-Voronoi cell).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .formats.capture import Capture
from .environment import generated, light_basis, relight
from .imageio import write_png
from .pictures import grid, label, tile8


def key_light(capture: Capture, camera) -> int:
    """Index of the light nearest to 35° up and 35° to the camera's left, from the subject."""
    fwd = -camera.forward  # subject → camera
    right = camera.R[0]
    up = -camera.R[1]
    want = fwd + 0.7 * up - 0.7 * right
    want /= np.linalg.norm(want)
    return int(np.argmax(capture.rig.lights.directions @ want))


def contact_sheet(capture_dir, out_png, camera: str | None = None, environment: str = "sky",
                  tile: int = 192, columns: int = 6, progress: bool = True) -> Path:
    """Write a PNG: per expression a pair of tiles (one light | relit), labelled (``progress``: a bar)."""
    from .progress import bar

    cap = Capture(capture_dir)
    cam = cap.rig.camera(camera) if camera else cap.rig.cameras[min(1, len(cap.rig.cameras) - 1)]
    key = key_light(cap, cam)
    weights = light_basis(generated(environment), cap.rig.lights.directions)
    tiles = []
    names = cap.expression_names

    def exposed(img):  # the brighter skin (90th percentile of lit pixels) at ~0.45 linear
        lit = img.max(axis=-1)
        level = np.percentile(lit[lit > 0], 90) if (lit > 0).any() else 1.0
        return img * (0.45 / max(level, 1e-6))

    for name in bar(names, progress, desc="contact sheet"):
        field = cap.field(name, cam.name)
        one = field[key]
        lit = relight(field, weights)
        tiles.append(label(tile8(exposed(one), size=tile), f"{name}: 1 light"))
        tiles.append(label(tile8(exposed(lit), size=tile), f"{name}: {environment}"))
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    write_png(out_png, grid(tiles, columns=columns if columns % 2 == 0 else columns + 1))
    return out_png
