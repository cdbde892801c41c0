"""A toy light-stage capture for testing the rendering chain independently of the synthetic head:
a textured sphere ('icosphere 4') in three 'expressions', photographed by a tiny simulated stage.
The template is icosphere 2, whose vertices are the first 162 vertices of icosphere 4, so its exact
position in every expression is known. The registration folder is written from that truth (this is
test code: it stands in for a perfect registration)."""
from __future__ import annotations

import numpy as np
import trimesh

from mifacerf.capture_folder import CaptureWriter, ExpressionEntry
from mifacerf.registered import RegisteredExpression, RegistrationWriter
from mifacerf.geometry.meshscene import MeshScene
from mifacerf.rig import LightStage, Rig, camera_ring
from mifacerf.synthetic.olat import render_olat
from mifacerf.variant import ensure_variant

FINE = trimesh.creation.icosphere(4, radius=0.09)
COARSE = trimesh.creation.icosphere(2, radius=0.09)
N_T = len(COARSE.vertices)
assert np.allclose(FINE.vertices[:N_T], COARSE.vertices)


def expression_vertices(name: str) -> np.ndarray:
    v = np.asarray(FINE.vertices, np.float64)
    if name == "neutral":
        return v.copy()
    if name == "stretch":
        return v * np.array([0.95, 1.12, 0.97])
    if name == "turn":
        a = np.radians(12.0)
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        return v @ R.T
    if name.startswith("mix"):  # an in-between: half stretch
        return v * np.array([0.975, 1.06, 0.985])
    raise KeyError(name)


def texture() -> np.ndarray:
    rng = np.random.default_rng(5)
    h, w = 128, 256
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.stack([0.55 + 0.1 * np.sin(xx / 7.0), 0.35 + 0.1 * np.cos(yy / 5.0), 0.3 + 0.05 * rng.random((h, w))], -1)
    spots = rng.random((h, w)) > 0.985
    base[spots] = [0.9, 0.85, 0.1]
    return base.astype(np.float32)


def scene_for(vertices: np.ndarray, mi):
    uv = np.stack([0.5 + np.arctan2(FINE.vertices[:, 0], FINE.vertices[:, 2]) / (2 * np.pi),
                   np.arccos(np.clip(FINE.vertices[:, 1] / 0.09, -1, 1)) / np.pi], 1)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "principled", "roughness": 0.6,
                                  "base_color": {"type": "bitmap", "bitmap": mi.Bitmap(texture()),
                                                 "raw": True}})
    mesh = mi.Mesh("toy", len(vertices), len(FINE.faces), props=props, has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    import drjit as dr
    p["vertex_positions"] = dr.ravel(mi.Point3f(np.ascontiguousarray(vertices.T, dtype=np.float32)))
    p["faces"] = dr.ravel(mi.Vector3u(np.ascontiguousarray(FINE.faces.T, dtype=np.uint32)))
    p["vertex_texcoords"] = dr.ravel(mi.Point2f(np.ascontiguousarray(uv.T, dtype=np.float32)))
    p.update()
    return {"toy": mesh}


def make_toy(root, names=("neutral", "stretch", "turn"), size=64, n_pos=8, n_str=6):
    """Write ROOT/capture (with ROOT/capture/registration from truth); returns (capture path, rig)."""
    mi = ensure_variant()
    lights = LightStage.semicircular_arm(n_pos, n_str, irradiance_spread=0.05, seed=2)
    cams = camera_ring([(-30, -6), (0, 10), (30, -6)], width=size, height=size, target=(0, 0, 0),
                       face_height=0.24)
    rig = Rig(lights, cams)
    cats = {"neutral": "neutral", "stretch": "mouth", "turn": "head_pose"}
    w = CaptureWriter(root / "capture", rig, [ExpressionEntry(n, cats.get(n, "other")) for n in names])
    for n in names:
        scene = mi.load_dict({"type": "scene", **scene_for(expression_vertices(n), mi)})
        for c in cams:
            imgs = render_olat(scene, c, lights.directions, lights.irradiance, spp=4)
            for l in range(len(lights)):
                w.write_image(n, c.name, l, imgs[l])
    w.finish()
    from mifacerf.capture_folder import Capture
    cap = Capture(root / "capture")
    template = {"n_vertices": N_T, "triangles": np.asarray(COARSE.faces).tolist(), "kinds": ["dot"] * N_T,
                "regions": {}}
    rw = RegistrationWriter(root / "capture" / "registration", cap, template)
    for n in names:
        v = expression_vertices(n)[:N_T]
        ms = MeshScene(v, COARSE.faces)
        uv = np.stack([c.project(v)[0] for c in cams]).astype(np.float32)
        vis = np.stack([ms.visible_from(v, c) for c in cams])
        rw.write_expression(RegisteredExpression(n, v, np.ones(N_T), uv, vis), {"registered": N_T})
    return root / "capture", rig
