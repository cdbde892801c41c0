"""Coverage of the truth foreground and time per frame of a model (issue 16: the template's extensions).

    python scripts/extension_coverage.py coverage MODEL TRUTH -o OUT.json [--png OUT.png]
    python scripts/extension_coverage.py timing BEFORE_MODEL AFTER_MODEL -o OUT.json [--repeat 3]

``coverage``: 13 fixed cases of the synthetic subject — (a) six captured expressions from capture
cameras, (c) four novel views 15-30 deg off, (d) three out-of-set meshes (seeded random controls) —
rendered at 256 px, 4 spp, under ``sky``. The truth's foreground is geometry only: the truth pose (its
controls from ``TRUTH/expressions/<name>.npz``, or the drawn ones) ray-cast as skin + eyes + teeth +
mouth interior at 16 stratified samples per pixel; per case the share of truth-foreground pixels the
render leaves uncovered (:func:`mifacerf.evaluation.metrics.uncovered`) and the silhouette IoU
(:func:`~mifacerf.evaluation.metrics.silhouette_iou`). A face-only model gets the first
``n_vertices`` of the subject's template as its out-of-set meshes (the face's vertices come first).
``--png``: per case the composite over the sky and a coverage map (grey both, red missed, blue extra).

``timing``: five frames (three captured, two novel views) rendered by both models in one process,
alternating ``--repeat`` times each after a warm-up (this shared machine's load varies); the minimum per
model and frame, and the mean ratio.
"""
from __future__ import annotations

import json
import time
from pathlib import Path

import click
import numpy as np

CASES = [("a", "neutral", "cam1"), ("a", "smile", "cam0"), ("a", "head_turn_left", "cam2"), ("a", "surprise", "cam4"),
         ("a", "anger", "cam3"), ("a", "viseme_aa", "cam5"),
         ("c", "neutral", (25, 0)), ("c", "smile", (-30, 5)), ("c", "head_up", (15, -7)), ("c", "disgust", (-20, 3)),
         ("d", 0, "cam1"), ("d", 1, "cam2"), ("d", 2, "cam0")]
TIMED = [("neutral", "cam1"), ("smile", "cam0"), ("surprise", "cam4"), ("anger", (25, 0)), ("head_up", (-30, 5))]


@click.group()
def main():
    pass


@main.command()
@click.argument("model", type=click.Path(exists=True, file_okay=False))
@click.argument("truth", type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False))
@click.option("--png", default=None, type=click.Path(dir_okay=False))
def coverage(model, truth, out, png):
    import mifacerf as mf
    from mifacerf.evaluation.metrics import silhouette_iou, uncovered
    from mifacerf.evaluation.render_cases import random_params
    from mifacerf.geometry.meshscene import MeshScene
    from mifacerf.synthetic.subject import default_subject

    face = mf.load_model(model)
    face.renderer.cache_frames = False
    subj = default_subject(256)
    n = face.model.n_vertices
    rng = np.random.default_rng(7)
    drawn = [random_params(subj, rng) for _ in range(3)]
    res, tiles = [], []
    for kind, ex, cam in CASES:
        camera = face.camera(cam, 256)
        params = drawn[ex] if kind == "d" else np.load(Path(truth) / "expressions" / f"{ex}.npz")["params"]
        pose = subj.pose(params, textures=False)
        kw = dict(mesh=pose.template_vertices[:n]) if kind == "d" else dict(expression=ex)
        Vs, Fs, off = [pose.skin_vertices], [subj.skin_faces], len(pose.skin_vertices)
        for p in pose.parts.values():
            Vs.append(p.vertices)
            Fs.append(np.asarray(p.faces) + off)
            off += len(p.vertices)
        hits, _ = MeshScene(np.concatenate(Vs), np.concatenate(Fs)).render_hits(camera, spp=16)
        ta = hits.valid.reshape(camera.height, camera.width, 16).mean(-1)
        t0 = time.perf_counter()
        rgba = face.render(**kw, camera=camera, env="sky", spp=4)
        dt = time.perf_counter() - t0
        a = rgba[..., 3]
        res.append({"kind": kind, "case": f"{ex}@{cam}", "uncovered": float(uncovered(a, ta)[0]),
                    "iou": float(silhouette_iou(a, ta)), "seconds": dt})
        click.echo(json.dumps(res[-1]))
        if png:
            rgb = np.clip(mf.composite(rgba, mf.environment_plate("sky", camera)), 0, 1) ** (1 / 2.2)
            cov = np.zeros(a.shape + (3,))
            cov[(a > 0.5) & (ta > 0.5)] = 0.5
            cov[(a <= 0.5) & (ta > 0.5)] = [1, 0, 0]
            cov[(a > 0.5) & (ta <= 0.5)] = [0, 0, 1]
            tiles.append(np.concatenate([rgb, cov], 0))
    summary = {}
    for k in "acd":
        r = [x for x in res if x["kind"] == k]
        summary[k] = {m: float(np.mean([x[m] for x in r])) for m in ("uncovered", "iou", "seconds")}
        summary[k]["uncovered_max"] = float(max(x["uncovered"] for x in r))
        summary[k]["iou_min"] = float(min(x["iou"] for x in r))
    click.echo(json.dumps(summary, indent=1))
    Path(out).write_text(json.dumps({"model": str(model), "cases": res, "summary": summary}, indent=1))
    if png:
        import imageio

        imageio.imwrite(png, (np.concatenate(tiles, 1) * 255).astype(np.uint8))


@main.command()
@click.argument("before", type=click.Path(exists=True, file_okay=False))
@click.argument("after", type=click.Path(exists=True, file_okay=False))
@click.option("-o", "--out", required=True, type=click.Path(dir_okay=False))
@click.option("--repeat", type=click.IntRange(min=1), default=3, show_default=True)
def timing(before, after, out, repeat):
    import mifacerf as mf

    models = {"before": mf.load_model(before), "after": mf.load_model(after)}
    for f in models.values():
        f.renderer.cache_frames = False
    rows = []
    for ex, cam in TIMED:
        t = {k: np.inf for k in models}
        for f in models.values():
            f.render(ex, camera=cam, env="sky", size=256, spp=4)       # warm: the fields are loaded
        for _ in range(repeat):
            for k, f in models.items():
                t0 = time.perf_counter()
                f.render(ex, camera=cam, env="sky", size=256, spp=4)
                t[k] = min(t[k], time.perf_counter() - t0)
        rows.append({"case": f"{ex}@{cam}", **t, "ratio": t["after"] / t["before"]})
        click.echo(json.dumps(rows[-1]))
    summary = {"before_mean_s": float(np.mean([r["before"] for r in rows])),
               "after_mean_s": float(np.mean([r["after"] for r in rows])),
               "ratio_mean": float(np.mean([r["ratio"] for r in rows]))}
    click.echo(json.dumps(summary))
    Path(out).write_text(json.dumps({"before": str(before), "after": str(after), "cases": rows, "summary": summary},
                                    indent=1))


if __name__ == "__main__":
    main()
