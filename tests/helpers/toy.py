"""The toy light-stage capture of the registration and rendering tests, independent of the synthetic
head: an ellipsoidal 'head' with painted yellow dots (a texture painted by 3-D distance, so dots are
round discs on the surface) in a few smoothly deformed 'expressions', photographed by a small stage.

The fine render mesh is icosphere 5 on the ellipsoid. Both templates are subsets of its vertices, so
their position in every expression is known exactly:

- the registration template (:func:`template_dict`): the dots (every dot centre is a fine vertex) plus
  a few non-dot vertices. The synthetic user (:func:`mifacerf.synthetic.hand_inputs.make_hand_inputs`)
  writes the hand inputs of every capture.
- the coarse template: icosphere 2, whose vertices are the first ``N_T`` = 162 fine vertices, all
  round the head. ``make_toy(..., truth_registration=True)`` writes the capture's registration folder
  from the truth on it (test code: it stands in for a perfect registration, so that rendering is
  tested apart from registration).
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import trimesh

from mifacerf.formats.capture import Capture, CaptureWriter, ExpressionEntry
from mifacerf.formats.registration import RegisteredExpression, RegistrationWriter
from mifacerf.geometry.meshscene import MeshScene
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

COARSE_FACES = np.asarray(trimesh.creation.icosphere(2, radius=1.0).faces, np.int64)
N_T = int(COARSE_FACES.max()) + 1
assert np.allclose(trimesh.creation.icosphere(2, radius=1.0).vertices, DIRS[:N_T])

CATEGORIES = {"neutral": "neutral", "stretch": "mouth", "bulge": "emotion", "turn": "head_pose",
              "pucker": "viseme"}


class Toy(NamedTuple):
    capture: object             # Path of ROOT/capture
    rig: Rig
    truth: dict                 # {expression: (T, 3) true positions of the registration template}


def _pick_dots(min_dist=0.011):
    """Dot centres: fine vertices on the front of the head, greedily spread ``min_dist`` apart."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    front = np.flatnonzero((DIRS[:, 2] > 0.25) & (np.abs(DIRS[:, 1]) < 0.85))
    order = rng.permutation(front)
    tree, row = cKDTree(REST[front]), {v: k for k, v in enumerate(front)}
    taken = np.zeros(len(front), bool)  # within min_dist of a chosen dot
    chosen = []
    for i in order:
        if not taken[row[i]]:
            chosen.append(i)
            taken[tree.query_ball_point(REST[i], min_dist)] = True
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
    if name == "mix":       # an in-between, never captured: half-way from the neutral to the stretch
        return 0.5 * (deform("neutral", X) + deform("stretch", X))
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


@functools.lru_cache(maxsize=1)
def texture(res=1024):
    """(res, 2 res, 3) texture over (azimuth, polar) with the dots painted by 3-D distance (cached: do not
    modify the array)."""
    h, w = res, 2 * res
    v = (np.arange(h) + 0.5) / h
    u = (np.arange(w) + 0.5) / w
    U, Vv = np.meshgrid(u, v)
    theta, phi = Vv * np.pi, (U - 0.5) * 2 * np.pi
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), np.sin(theta) * np.cos(phi)], -1)
    P = d * AXES
    from scipy.spatial import cKDTree

    texel = 2 * np.pi * AXES.max() / w
    # texels farther than DOT_RADIUS + texel from every dot are skin (cover 0): no need of their distance
    dist, _ = cKDTree(REST[DOTS]).query(P.reshape(-1, 3), distance_upper_bound=DOT_RADIUS + texel)
    cover = np.clip((DOT_RADIUS - dist) / (1.5 * texel) + 0.5, 0, 1).reshape(h, w, 1)
    rng = np.random.default_rng(1)
    skin = SKIN * (1 + 0.06 * (rng.random((h, w, 1)) - 0.5))
    return (skin * (1 - cover) + YELLOW * cover).astype(np.float32)


def uvs():
    theta = np.arccos(np.clip(DIRS[:, 1], -1, 1))
    phi = np.arctan2(DIRS[:, 0], DIRS[:, 2])
    return np.stack([phi / (2 * np.pi) + 0.5, theta / np.pi], 1)


def scene_for(vertices, mi) -> dict:
    """Scene-dict entries ``{"toy": mesh}`` of the textured fine mesh at ``vertices`` (fine, (V, 3))."""
    import drjit as dr

    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "principled", "roughness": 0.45, "specular": 0.5,
                                  "base_color": {"type": "bitmap", "bitmap": mi.Bitmap(texture()), "raw": True}})
    mesh = mi.Mesh("toy", len(vertices), len(FACES), props=props, has_vertex_texcoords=True)
    p = mi.traverse(mesh)
    p["vertex_positions"] = dr.ravel(mi.Point3f(np.ascontiguousarray(vertices.T, dtype=np.float32)))
    p["faces"] = dr.ravel(mi.Vector3u(np.ascontiguousarray(FACES.T, dtype=np.uint32)))
    p["vertex_texcoords"] = dr.ravel(mi.Point2f(np.ascontiguousarray(uvs().T, dtype=np.float32)))
    p.update()
    return {"toy": mesh}


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


def write_truth_registration(capture, names) -> None:
    """CAPTURE/registration written from the truth on the coarse template (test code only)."""
    cap = Capture(capture)
    cams = cap.rig.cameras
    template = {"n_vertices": N_T, "triangles": COARSE_FACES.tolist(), "kinds": ["dot"] * N_T, "regions": {}}
    rw = RegistrationWriter(capture / "registration", cap, template)
    for n in names:
        v = deform(n)[:N_T]
        ms = MeshScene(v, COARSE_FACES)
        uv = np.stack([c.project(v)[0] for c in cams]).astype(np.float32)
        vis = np.stack([ms.visible_from(v, c) for c in cams])
        rw.write_expression(RegisteredExpression(n, v, np.ones(N_T), uv, vis), {"registered": N_T})


def make_toy(root, names=("neutral", "stretch", "bulge"), size=96, n_pos=8, n_str=6, seed=0,
             truth_registration=False) -> Toy:
    """Write ROOT/capture (images, rig, hand/ inputs; with ``truth_registration`` also
    ROOT/capture/registration from the truth) of the expressions ``names``, photographed by three
    ``size`` px cameras under an ``n_pos`` x ``n_str`` light arm."""
    mi = ensure_variant()
    lights = LightStage.semicircular_arm(n_pos, n_str, irradiance_spread=0.05, seed=2)
    cams = camera_ring([(-35, -8), (0, 12), (35, -8)], width=size, height=size, target=(0, 0, 0.0),
                       face_height=0.22, distance=1.0)
    rig = Rig(lights, cams)
    w = CaptureWriter(root / "capture", rig, [ExpressionEntry(n, CATEGORIES.get(n, "other")) for n in names])
    tpl, ids = template_dict()
    truths, truth_T = [], {}
    for n in names:
        V = deform(n)
        scene = mi.load_dict({"type": "scene", **scene_for(V, mi)})
        for c in cams:
            imgs = render_olat(scene, c, lights.directions, lights.irradiance, spp=4)
            for l in range(len(lights)):
                w.write_image(n, c.name, l, imgs[l])
        truth_T[n] = V[ids]
        truths.append(TruthExpression(n, V[ids], (V, FACES)))
    make_hand_inputs(root / "capture", tpl, truths, rig, seed=seed)
    w.finish()
    if truth_registration:
        write_truth_registration(root / "capture", names)
    return Toy(root / "capture", rig, truth_T)
