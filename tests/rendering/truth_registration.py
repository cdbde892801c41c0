"""A perfect 'registration' written from the synthetic truth — test/measurement code only.

It lets the rendering chain be tested and measured apart from registration errors: the
template vertices come from OUT/truth (exact), texture coordinates and visibility are
computed from them like registration does, and no dots are removed.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mifacerf.capture_folder import Capture
from mifacerf.registered import RegisteredExpression, RegistrationWriter
from mifacerf.rendering.meshscene import MeshScene


def write_truth_registration(out, dest=None) -> Path:
    out = Path(out)
    cap = Capture(out / "capture")
    template = json.loads((out / "capture" / "hand" / "template.json").read_text()) \
        if (out / "capture" / "hand" / "template.json").exists() else None
    if template is None:
        from mifacerf.synthetic import default_subject

        template = json.loads(default_subject().template.to_json())
    tri = np.asarray(template["triangles"])
    dest = Path(dest or out / "truth_registration")
    rw = RegistrationWriter(dest, cap, template)
    scene = None
    for name in cap.expression_names:
        z = np.load(out / "truth" / "expressions" / f"{name}.npz")
        v = z["template_vertices"]
        scene = scene or MeshScene(v, tri)
        scene.set_vertices(v)
        uv = np.stack([c.project(v)[0] for c in cap.rig.cameras]).astype(np.float32)
        vis = np.stack([scene.visible_from(v, c) for c in cap.rig.cameras])
        eyes = np.full((2, 3), np.nan)
        for i, eye in enumerate(("eye_left", "eye_right")):
            key = f"part_{eye}"
            if key in z and eye in template.get("eyes", {}):
                c = np.asarray(template["eyes"][eye]["centre"])
                eyes[i] = (z[key] @ np.append(c, 1.0))[:3]
        teeth = np.stack([z.get(f"part_teeth_{k}", np.full((4, 4), np.nan)) for k in ("upper", "lower")])
        head = z["part_teeth_upper"] if "part_teeth_upper" in z else np.eye(4)  # rigid with the skull
        rw.write_expression(RegisteredExpression(name, v, np.ones(len(v)), uv, vis, eyes, teeth, head),
                            {"source": "truth"})
    return dest
