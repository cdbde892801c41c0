"""Measure a head through the pipeline (docs/your-own-head.md, "Measured"): per expression the share of
fiducials registered, then for captured expressions rendered from the model in capture cameras against
the dot-free path-traced truth: face-mask PSNR, composite PSNR (over a grey plate), the share of the
visible templated skin the model covers, eye and teeth pixels in the truth and the render, and for a
mesh subject the ears' pixels in the truth and how many the model covers. Writes
OUT_JSON and, beside it, render | truth | uncovered PNGs to look at::

    python scripts/measure_own_head.py SYNTH_OUT MODEL OUT_JSON [EXPRESSION ...] [--env sky] [--spp-truth 64]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("synth")
    ap.add_argument("model")
    ap.add_argument("out")
    ap.add_argument("expressions", nargs="*")
    ap.add_argument("--env", default="sky")
    ap.add_argument("--spp-truth", type=int, default=64)
    ap.add_argument("--cameras", default="1")
    a = ap.parse_args()

    import mifacerf as mf
    from mifacerf.environment import resolve
    from mifacerf.evaluation.masks import classify_pixels, face_mask, triangle_mask
    from mifacerf.evaluation.metrics import composite_psnr, psnr
    from mifacerf.imageio import to_srgb8, write_png
    from mifacerf.synthetic.scene import PART_IDS
    from mifacerf.synthetic.truth_scene import TruthRenderer

    synth = Path(a.synth)
    reg = json.loads((synth / "capture" / "registration" / "registration.json").read_text())
    result = {"registered_fraction": {k: v.get("registered_fraction") for k, v in reg["expressions"].items()},
              "registration_s": {k: v.get("time_s") for k, v in reg["expressions"].items()}, "renders": []}
    t0 = time.time()
    face = mf.load_model(a.model)
    tr = TruthRenderer.from_synth(synth)
    result["load_s"] = time.time() - t0
    env = resolve(a.env)
    names = a.expressions or list(tr.expressions)
    plate = np.full((1, 1, 3), 0.18)
    ears = _ear_triangles(tr.subject)
    for name in names:
        for ci in [int(c) for c in a.cameras.split(",")]:
            cam = face.model.cameras[ci]
            t = time.time()
            img = face.render(name, camera=cam, env=env, spp=4)
            t_render = time.time() - t
            p = tr.expressions[name]
            t = time.time()
            gt = tr.render(p, cam, env, spp=a.spp_truth, seed=5)
            t_truth = time.time() - t
            tr.scene(env).set_pose(tr.subject.pose(p))
            cl = classify_pixels(tr.scene(env), cam)
            mask = face_mask(cl)
            skin = cl["face"].all(axis=2)
            pl = np.broadcast_to(plate, img.shape[:2] + (3,))
            eyes_t = int(np.isin(cl["part"], [PART_IDS["eye_left"], PART_IDS["eye_right"]]).all(axis=2).sum())
            teeth_t = int(np.isin(cl["part"], [PART_IDS["teeth_upper"], PART_IDS["teeth_lower"]]).all(axis=2).sum())
            row = {"expression": name, "camera": cam.name, "size": [cam.width, cam.height],
                   "psnr_face_mask": psnr(img, gt, mask), "psnr_composite": composite_psnr(img, gt, pl),
                   "face_mask_px": int(mask.sum()),
                   "covered_visible_skin": float((img[..., 3][skin] > 0.5).mean()) if skin.any() else None,
                   "eye_px_truth": eyes_t, "teeth_px_truth": teeth_t,
                   "eye_px_rendered": int((img[..., 3] > 0.5)[np.isin(cl["part"], [PART_IDS["eye_left"],
                                                                                 PART_IDS["eye_right"]]).all(axis=2)].sum()),
                   "render_s": t_render, "truth_s": t_truth}
            if ears is not None:       # the ears' skin (mesh_template.ear_zones) in the truth, and the share the model covers
                em = triangle_mask(cl, ears)
                row["ear_px_truth"] = int(em.sum())
                row["ear_px_covered"] = int((em & (img[..., 3] > 0.5)).sum())
            result["renders"].append(row)
            print(json.dumps(row))
            miss = np.zeros(img.shape[:2] + (3,), np.float32)
            miss[skin & ~(img[..., 3] > 0.5)] = [1, 0, 1]
            strip = np.concatenate([img[..., :3] + (1 - img[..., 3:]) * 0.18, gt[..., :3] + (1 - gt[..., 3:]) * 0.18,
                                    miss], axis=1)
            write_png(Path(a.out).with_name(f"{Path(a.out).stem}_{name}_{cam.name}.png"), strip)
    Path(a.out).write_text(json.dumps(result, indent=1))


def _ear_triangles(subject):
    """(F,) bool the skin triangles of the ears of a mesh subject (None: no ear marks, or not a mesh subject)."""
    from mifacerf.synthetic.mesh_template import ear_zones

    t = getattr(subject, "template", None)
    if getattr(subject, "kind", None) != "mesh" or t is None or not {"ear_L", "ear_R"} & set(t.names):
        return None
    marks = [t.neutral[t.names.index(n)] for n in ("ear_L", "ear_R") if n in t.names]
    return ear_zones(subject.skin_rest, subject.skin_faces, marks)


if __name__ == "__main__":
    main()
