"""A toy subject for registration tests, independent of the synthetic head: an ellipsoidal
'head' with painted yellow dots (a texture painted by 3-D distance, so dots are round discs
on the surface) in a few smoothly deformed 'expressions', photographed by a small stage.

Every dot centre is a vertex of the fine render mesh, so its position in every expression
is known exactly. The template is the dots plus a few non-dot vertices; the synthetic user
(:func:`mifacerf.synthetic.hand_inputs.make_hand_inputs`) writes the hand inputs.
"""
from __future__ import annotations

import numpy as np
import trimesh

from mifacerf.capture_folder import CaptureWriter, ExpressionEntry
from mifacerf.rig import LightStage, Rig, camera_ring
from mifacerf.synthetic.hand_inputs import TruthExpression, make_hand_inputs
from mifacerf.synthetic.olat import render_olat
from mifacerf.variant import ensure_variant

AXES = np.array([0.075, 0.095, 0.085])
DOT_RADIUS = 0.0021
SKIN = np.array([0.55, 0.36, 0.28])
YELLOW = np.array([0.85, 0.80, 0.12])
UNIT = trimesh.creation.icosphere(5, radius=1.0)
DIRS = np.asarray(UNIT.vertices, np.float64)
FACES = np.asarray(UNIT.faces, np.int64)
REST = DIRS * AXES

CATEGORIES = {"neutral": "neutral", "stretch": "mouth", "bulge": "emotion", "turn": "head_pose",
              "pucker": "viseme"}


def _pick_dots(min_dist=0.011):
    """Dot centres: fine vertices on the front of the head, greedily spread ``min_dist`` apart."""
    rng = np.random.default_rng(3)
    front = np.flatnonzero((DIRS[:, 2] > 0.25) & (np.abs(DIRS[:, 1]) < 0.85))
    order = rng.permutation(front)
    chosen = []
    for i in order:
        if all(np.linalg.norm(REST[i] - REST[j]) > min_dist for j in chosen):
            chosen.append(i)
    return np.array(sorted(chosen))


DOTS = _pick_dots()


def deform(name: str, X: np.ndarray | None = None) -> np.ndarray:
    """The expression's deformation of rest points X (default: the fine mesh)."""
    X = REST if X is None else np.asarray(X, np.float64)
    if name == "neutral":
        return X.copy()
    if name == "stretch":   # jaw-like: the lower half stretches down
        s = 1.0 + 0.10 * np.clip(-X[:, 1] / AXES[1], 0, 1) ** 2
        return X * np.stack([np.ones(len(X)), s, np.ones(len(X))], 1)
    if name == "bulge":     # a cheek bulging out and up by ~5 mm
        c = np.array([0.04, -0.02, 0.07])
        g = np.exp(-np.sum((X - c) ** 2, 1) / (2 * 0.025 ** 2))
        n = X / AXES ** 2
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return X + g[:, None] * (0.005 * n + np.array([0, 0.004, 0]))
    if name == "pucker":    # the lower-front pushed forward and narrowed
        c = np.array([0.0, -0.045, 0.08])
        g = np.exp(-np.sum((X - c) ** 2, 1) / (2 * 0.02 ** 2))
        return X + g[:, None] * np.array([0, 0, 0.006]) - g[:, None] * 0.15 * (X - c) * np.array([1, 0, 0])
    if name == "turn":      # head turn 10 degrees about a neck pivot, plus the bulge
        a = np.radians(10.0)
        R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        p = np.array([0.0, -0.08, -0.02])
        return (deform("bulge", X) - p) @ R.T + p
    raise KeyError(name)


def texture(res=1024):
    """(res, 2 res, 3) texture over (azimuth, polar) with the dots painted by 3-D distance."""
    h, w = res, 2 * res
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    U, Vv = np.meshgrid(u, v)
    theta, phi = Vv * np.pi, (U - 0.5) * 2 * np.pi
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), np.sin(theta) * np.cos(phi)], -1)
    P = d * AXES
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(REST[DOTS]).query(P.reshape(-1, 3))
    texel = 2 * np.pi * AXES.max() / w
    cover = np.clip((DOT_RADIUS - dist) / (1.5 * texel) + 0.5, 0, 1).reshape(h, w, 1)
    rng = np.random.default_rng(1)
    skin = SKIN * (1 + 0.06 * (rng.random((h, w, 1)) - 0.5))
    return (skin * (1 - cover) + YELLOW * cover).astype(np.float32)


def uvs():
    theta = np.arccos(np.clip(DIRS[:, 1], -1, 1))
    phi = np.arctan2(DIRS[:, 0], DIRS[:, 2])
    return np.stack([phi / (2 * np.pi) + 0.5, theta / np.pi], 1)


def scene_for(vertices, mi, tex):
    import drjit as dr

    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "principled", "roughness": 0.45, "specular": 0.5,
                                  "base_color": {"type": "bitmap", "bitmap": mi.Bitmap(tex), "raw": True}})
    mesh = mi.Mesh("toy", len(vertices), len(FACES), props=props, has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = dr.ravel(mi.Point3f(np.ascontiguousarray(vertices.T, dtype=np.float32)))
    p["faces"] = dr.ravel(mi.Vector3u(np.ascontiguousarray(FACES.T, dtype=np.uint32)))
    # flip v: Mitsuba's bitmap row 0 is v = 0 at the top? (uv (0,0) is the first texel row)
    p["vertex_texcoords"] = dr.ravel(mi.Point2f(np.ascontiguousarray(uvs().T, dtype=np.float32)))
    p.update()
    return mi.load_dict({"type": "scene", "toy": mesh})


def template_dict():
    """Canonical template dict with the neutral's true positions (the hand-input writer perturbs them)."""
    from scipy.spatial import Delaunay

    extra = np.flatnonzero((DIRS[:, 2] > 0.5) & (np.abs(DIRS[:, 0]) < 0.05) & (DIRS[:, 1] < 0.0))[:3]
    ids = np.concatenate([DOTS, extra])
    V = REST[ids]
    az = np.arctan2(V[:, 0], V[:, 2])
    el = np.arcsin(np.clip(V[:, 1] / AXES[1], -1, 1))
    tri = Delaunay(np.stack([az, el], 1)).simplices
    kinds = ["dot"] * len(DOTS) + ["skin"] * len(extra)
    # coarse points: dots nearest to a 4 x 4 grid of directions
    coarse = []
    for a in np.radians([-45, -15, 15, 45]):
        for e in np.radians([-40, -12, 16, 44]):
            k = int(np.argmin((az[:len(DOTS)] - a) ** 2 + (el[:len(DOTS)] - e) ** 2))
            if k not in coarse:
                coarse.append(k)
    return {"schema": "mifacerf.template/1", "subject": "toy",
            "vertices": [{"kind": k, "name": f"v{i}", "position": p.tolist()} for i, (k, p) in enumerate(zip(kinds, V))],
            "triangles": tri.tolist(), "coarse_points": coarse, "regions": {},
            "dot_radius": DOT_RADIUS}, ids


def make_toy(root, names=("neutral", "stretch", "bulge"), size=96, n_pos=8, n_str=6, seed=0):
    """Write ROOT/capture (with hand/) and return (capture path, truth {name: (T, 3) template truth})."""
    mi = ensure_variant()
    lights = LightStage.semicircular_arm(n_pos, n_str, irradiance_spread=0.05, seed=2)
    cams = camera_ring([(-35, -8), (0, 12), (35, -8)], width=size, height=size, target=(0, 0, 0.0),
                       face_height=0.22, distance=1.0)
    rig = Rig(lights, cams)
    w = CaptureWriter(root / "capture", rig, [ExpressionEntry(n, CATEGORIES.get(n, "other")) for n in names])
    tex = texture()
    tpl, ids = template_dict()
    truths, truth_T = [], {}
    for n in names:
        V = deform(n)
        scene = scene_for(V, mi, tex)
        for c in cams:
            imgs = render_olat(scene, c, lights.directions, lights.irradiance, spp=4)
            for l in range(len(lights)):
                w.write_image(n, c.name, l, imgs[l])
        truth_T[n] = V[ids]
        truths.append(TruthExpression(n, V[ids], (V, FACES)))
    make_hand_inputs(root / "capture", tpl, truths, rig, seed=seed)
    w.finish()
    return root / "capture", truth_T
