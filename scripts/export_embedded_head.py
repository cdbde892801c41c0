"""Export the embedded synthetic head as a ``mifacerf synth --subject`` folder: one multi-part OBJ in
centimetres (groups Face, Eyeball left/right, Teeth, Mouth socket; per-corner UVs from its atlas),
one OBJ per expression (its skin and parts posed), its dot-free albedo as ``albedo.png`` and a
``subject.json`` (scale 0.01, placement as_is). Used to measure the loader on a head whose truth is
known (docs/your-own-head.md)::

    python scripts/export_embedded_head.py OUT_FOLDER [EXPRESSION ...]

Only expressions without a head turn are exported (blendshapes cannot rotate the head).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

PARTS = (("eye_left", "Eyeball left"), ("eye_right", "Eyeball right"), ("teeth_upper", "Teeth"),
         ("teeth_lower", "Teeth"), ("mouth_interior", "Mouth socket"))
DEFAULT = ("viseme_aa", "teeth_bared", "eyes_closed", "smile")


def _positions(subj, pose):
    P = [pose.skin_vertices] + [pose.parts[k].vertices for k, _ in PARTS]
    return np.concatenate(P) * 100.0


def main(out: str, names=DEFAULT) -> None:
    import imageio.v3 as iio

    from mifacerf.imageio import to_srgb8
    from mifacerf.synthetic import default_subject

    subj = default_subject()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    neutral = subj.neutral
    sizes = [len(neutral.skin_vertices)] + [len(neutral.parts[k].vertices) for k, _ in PARTS]
    offs = np.concatenate([[0], np.cumsum(sizes)])
    faces = ["g Face"] + [f"f {a + 1}/{ta + 1} {b + 1}/{tb + 1} {c + 1}/{tc + 1}" for (a, b, c), (ta, tb, tc)
                          in zip(subj.skin_faces.tolist(), subj.skin_uv_faces.tolist())]
    last = None
    for i, (k, g) in enumerate(PARTS):
        if g != last:
            faces.append(f"g {g}")
            last = g
        o = offs[i + 1]
        faces += [f"f {a + o + 1} {b + o + 1} {c + o + 1}" for a, b, c in neutral.parts[k].faces.tolist()]
    vt = [f"vt {u:.7f} {v:.7f}" for u, v in subj.skin_uv]
    by_name = {e.name: e for e in subj.presets("paper")}
    wrote = []
    for name in ["neutral"] + list(names):
        e = by_name[name]
        pose = subj.pose(e.params, textures=False)
        if not np.allclose(pose.transforms["head"], np.eye(4), atol=1e-9):
            print(f"skipped {name}: it turns the head")
            continue
        V = _positions(subj, pose)
        lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in V]
        (out / f"{name}.obj").write_text("\n".join(lines + vt + faces) + "\n")
        wrote.append(name)
    albedo = subj.without_dots().neutral.textures.albedo          # texel row 0 = v 0
    iio.imwrite(out / "albedo.png", to_srgb8(albedo[::-1]))        # image files: row 0 = v 1
    (out / "subject.json").write_text(json.dumps({
        "neutral": "neutral.obj", "expressions": {n: f"{n}.obj" for n in wrote if n != "neutral"},
        "scale": 0.01, "placement": "as_is", "source": "mifacerf's embedded head"}, indent=1))
    print(f"{out}: {', '.join(wrote)}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:] or DEFAULT)
