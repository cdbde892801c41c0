"""The traced surface side by side: flat triangles against their Phong surface (``Renderer(curved=n)``), on a
model's own registered geometry and on the truth's template vertices (evaluation only: an oracle of the
geometry), one draw of the evaluation's cases::

    python scripts/curved_outline.py SYNTH_OUT MODEL [--seed S] [--env sky] [--levels 1,2,3] [-n 1] [--scene]

``SYNTH_OUT`` a ``mifacerf synth`` folder (the main job's output folder holds one), ``MODEL`` a model built
from its capture. Prints per case, geometry and level: composite PSNR over the environment's plate,
silhouette IoU, the silhouette band's share of the composite error, mean |Δα| and mean Δα in the band
(+: the render's outline outside the truth's), and the warm frame's seconds (256², 4 spp; the truth 256 spp).
``--scene``: the model's rows rendered as a Mitsuba scene (a ``facerf_face`` shape at each level under the
``facerf`` integrator, as ``mi.load_dict`` gives a user), not by the Python renderer, and every case on its
camera without lens distortion (Mitsuba's sensor has none); no truth-vertex rows.
"""
from __future__ import annotations

import time

import click
import numpy as np


@click.command()
@click.argument("synth_out", type=click.Path(exists=True, file_okay=False))
@click.argument("model", type=click.Path(exists=True, file_okay=False))
@click.option("--seed", type=int, default=2026120218, show_default=True)
@click.option("--env", default="sky", show_default=True)
@click.option("--levels", default="1,2,3", show_default=True)
@click.option("-n", type=click.IntRange(min=1), default=1, show_default=True, help="Cases per kind.")
@click.option("--scene", is_flag=True, help="Render through the Mitsuba plugins (facerf_face + facerf).")
def main(synth_out, model, seed, env, levels, n, scene):
    from mifacerf.camera import Camera
    from mifacerf.evaluation.masks import classify_pixels, face_mask
    from mifacerf.evaluation.metrics import composite_psnr, over, region_map, silhouette_iou
    from mifacerf.evaluation.render_cases import draw_cases
    from mifacerf.rendering.api import environment_plate, load_model
    from mifacerf.rendering.renderer import Renderer
    from mifacerf.synthetic.truth_scene import TruthRenderer

    tr, face = TruthRenderer.from_synth(synth_out), load_model(model)
    renderers = {int(k): Renderer(face.model, curved=int(k), cache_frames=False) for k in levels.split(",")}
    means = {}
    for case in draw_cases(tr, face.model, np.random.default_rng(seed), n):
        cam = case.camera.resized(256, 256)
        if scene:   # Mitsuba's perspective sensor has no lens distortion: every row on the undistorted camera
            cam = Camera(cam.name, cam.width, cam.height, cam.K, np.zeros(5), cam.R, cam.t)
        truth = tr.render(case.params, cam, env, spp=256, seed=5)
        plate = environment_plate(face.environment(env), cam)
        fm = face_mask(classify_pixels(tr.scene(face.environment(env)), cam, spp=4))
        target, W = face.target(case.expression, case.mesh)
        parts = face.parts(case.expression, case.mesh)
        oracle = tr.subject.pose(case.params, textures=False).template_vertices[:face.model.n_vertices]
        click.echo(case.label)
        # (d) is rendered on the truth's mesh already: its "model" row is the oracle
        rows = (("model", target),) + ((("truth vertices", oracle),) if case.kind != "d" and not scene else ())
        for geometry, V in rows:
            for level, r in renderers.items():
                render = (lambda: _scene_render(model, case, cam, env, level)) if scene else \
                    (lambda: r.render(V, W, cam, face.environment(env), spp=4, parts=parts))
                render()        # warm
                t0 = time.perf_counter()
                img = render()
                seconds = time.perf_counter() - t0
                lab = region_map(img[..., 3], truth[..., 3], fm)
                band = lab == 3
                da = (img[..., 3] - truth[..., 3])[band]
                se = ((over(img, plate) - over(truth, plate)) ** 2).sum(-1)
                cp = composite_psnr(img, truth, plate)
                means.setdefault((geometry, level), []).append(cp)
                click.echo(f"  {geometry:14s} curved={level}: composite {cp:.2f} dB, IoU "
                           f"{silhouette_iou(img[..., 3], truth[..., 3]):.4f}, band share "
                           f"{se[band].sum() / se[lab > 0].sum():.2f}, band mean |da| {np.abs(da).mean():.3f}, "
                           f"mean da {da.mean():+.3f}, {seconds:.3f} s")
    for (geometry, level), v in means.items():
        click.echo(f"mean composite, {geometry}, curved={level}: {np.mean(v):.2f} dB over {len(v)} cases")


_SCENES: dict = {}


def _scene_render(model, case, cam, env, level):
    """(H, W, 4) the case through plain Mitsuba: ``facerf_face`` at Phong level ``level``, the ``facerf``
    integrator, the environment's cached EXR (background hidden, so alpha is the face's coverage)."""
    import tempfile

    from mifacerf.environment import cache_dir, generated
    from mifacerf.rendering.sensors import sensor_dict
    from mifacerf.variant import ensure_plugins

    mi = ensure_plugins()
    key = (case.label, level)
    if key not in _SCENES:
        generated(env)
        face = {"type": "facerf_face", "model": str(model), "curved": level}
        if case.mesh is not None:
            path = tempfile.mkdtemp() + "/target.npy"
            np.save(path, np.asarray(case.mesh))
            face["target"] = path
        else:
            e = case.expression
            face["expression"] = e if isinstance(e, str) else ",".join(f"{k}={w}" for k, w in e.items())
        _SCENES[key] = mi.load_dict({
            "type": "scene", "sensor": sensor_dict(cam, spp=4), "face": face,
            "env": {"type": "envmap", "filename": str(cache_dir() / "environments" / f"{env}-128.exr")},
            "integrator": {"type": "facerf", "nested": {"type": "path", "hide_emitters": True}}})
    return np.asarray(mi.render(_SCENES[key]))


if __name__ == "__main__":
    main()
