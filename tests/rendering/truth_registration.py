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
        rw.write_expression(RegisteredExpression(name, v, np.ones(len(v)), uv, vis), {"source": "truth"})
    return dest
