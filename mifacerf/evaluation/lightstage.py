"""Proof that the conventions are right: relit OLAT images against path-traced ground truth.

:func:`layout_vs_truth`: the subject OLAT-rendered with a light layout and relit by the plain
weighted sum of those images — each weight the environment's radiance integrated over that
light's spherical-Voronoi cell (:func:`mifacerf.environment.light_basis`) — must match the
subject path-traced (Mitsuba, same light transport and camera) under the environment. The
remaining difference is the light stage's discretisation of the environment (the only error the
light stage itself makes) and the truth's Monte Carlo noise. PSNR on the template's skin (:mod:`.masks`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..formats.capture import Capture
from ..environment import Environment, light_basis, relight, resolve
from .masks import classify_pixels
from .metrics import psnr


def _subject_view(out, expression: str | None, camera: str | None):
    """(capture, TruthRenderer, expression name, camera) of a synth output; defaults: the first captured
    expression, the second camera."""
    from ..synthetic.truth_scene import TruthRenderer

    out = Path(out)
    cap = Capture(out / "capture")
    expression = expression or cap.expression_names[0]
    cam = cap.rig.camera(camera) if camera else cap.rig.cameras[min(1, len(cap.rig.cameras) - 1)]
    return cap, TruthRenderer.from_synth(out), expression, cam


def layout_vs_truth(out, layouts: dict, environments, expression: str | None = None, camera: str | None = None,
                    spp_truth: int = 1024, spp: int = 4) -> list[dict]:
    """Light-stage design: how well each light layout can relight the subject at all.

    ``layouts`` {name: (L, 3) world unit directions towards the lights}. For each layout and
    environment, the subject (dots washed off, as the model renders it) is OLAT-rendered with
    those lights, relit by their spherical-Voronoi weights and compared with the path-traced
    truth on the template's skin (eyes and teeth excluded: their captured highlights are
    re-synthesised by the renderer). The error is the discretisation of the environment alone.
    """
    from ..synthetic.olat import render_olat

    _, tr, expression, cam = _subject_view(out, expression, camera)
    rows = []
    for env in environments:
        env = env if isinstance(env, Environment) else resolve(str(env))
        truth = 0.5 * sum(tr.render(tr.expressions[expression], cam, env, spp=spp_truth, seed=s) for s in (11, 12))
        sc = tr.scene(env)
        sc.set_pose(tr.subject.pose(tr.expressions[expression]))
        skin = classify_pixels(sc, cam)["face"].all(axis=2) & (truth[..., 3] > 0.999)
        for name, dirs in layouts.items():
            dirs = np.asarray(dirs, np.float64)
            relit = relight(render_olat(sc.scene, cam, dirs, spp=spp), light_basis(env, dirs))
            rows.append({"layout": name, "lights": len(dirs), "environment": env.name, "expression": expression,
                         "camera": cam.name, "psnr": psnr(relit, truth, skin), "pixels": int(skin.sum())})
    return rows

