"""Fiducial dots and the registration template of the procedural subject."""
import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from mifacerf.synthetic import Template, default_subject
from mifacerf.synthetic import head as H
from mifacerf.synthetic.template import COARSE_NAMES, REGION_NAMES, triangle_quality
from mifacerf.synthetic.textures import DOT_COLOUR, vermilion_mask


@pytest.fixture(scope="module")
def subj():
    return default_subject()


def test_dots_count_spacing_and_placement(subj):
    F = subj.skin_faces
    tri, bary = subj.dot_tri, subj.dot_bary
    assert 280 <= len(tri) <= 320
    assert tri.min() >= 0 and tri.max() < len(F)
    assert np.all(bary >= 0) and np.allclose(bary.sum(1), 1)
    P = subj.dots_neutral
    np.testing.assert_allclose(P, subj.neutral.dots, atol=1e-12)
    d, _ = cKDTree(P).query(P, k=2)
    assert d[:, 1].min() > 0.006                      # >= 6 mm apart (3 mm dots)
    assert np.median(d[:, 1]) > 0.009                 # spread evenly
    # on the face and neck: in front of the ears, below the hairline, above the neck base
    assert P[:, 2].min() > -0.03 and P[:, 1].min() > H.NECK_BASE_Y and P[:, 1].max() < 0.09
    assert (P[:, 1] < -0.11).sum() > 20 and (P[:, 1] > 0.03).sum() > 20   # neck and forehead
    # never on the red of the lips, in the eyes or the mouth
    assert vermilion_mask(P).max() == 0.0
    ms = subj.grid.slits["mouth"]
    lips = subj.neutral_skin[np.concatenate([ms.upper, ms.lower])]
    assert cKDTree(lips).query(P)[0].min() > 0.004
    for c in subj.eye_centres.values():
        assert np.linalg.norm(P - c, axis=1).min() > 0.018
    assert subj.dot_radius == pytest.approx(0.0015)


def test_dots_are_painted_yellow(subj):
    alb = subj.tex.albedo
    res = alb.shape[0]
    uv = np.einsum("nk,nkj->nj", subj.dot_bary, subj.skin_uv[subj.skin_uv_faces[subj.dot_tri]])
    px = np.clip((uv * res).astype(int), 0, res - 1)
    col = alb[px[:, 1], px[:, 0]]
    assert np.abs(col - DOT_COLOUR).max(axis=1).mean() < 0.05
    # and the skin a few millimetres away is not yellow
    assert np.mean(alb[..., 2]) > 0.1


def test_dots_move_with_the_skin(subj):
    p = subj.params(smile_L=1, jaw_open=0.2, head_yaw=0.3)
    pose = subj.pose(p, textures=False)
    F = subj.skin_faces
    want = np.einsum("nk,nkj->nj", subj.dot_bary, pose.skin_vertices[F[subj.dot_tri]])
    np.testing.assert_allclose(pose.dots, want)
    assert np.abs(pose.dots - subj.neutral.dots).max() > 0.01


def test_template_vertices_and_kinds(subj):
    t = subj.template
    kinds = np.array(t.kinds)
    assert (kinds == "dot").sum() == len(subj.dot_tri)
    for k in ("lip_upper", "lip_lower", "lip_corner", "lid_upper", "lid_lower", "lid_corner", "nostril",
              "ear", "nose_bridge"):
        assert (kinds == k).sum() >= 1, k
    assert (kinds == "lip_corner").sum() == 2 and (kinds == "lid_corner").sum() == 4
    assert (kinds == "ear").sum() == 2 and (kinds == "nose_bridge").sum() == 1
    # every template vertex is a surface point whose truth position is exact in any pose
    np.testing.assert_allclose(subj.neutral.template_vertices, t.neutral, atol=1e-12)
    pose = subj.pose(subj.params(jaw_open=0.25, blink_L=1), textures=False)
    np.testing.assert_allclose(pose.template_vertices, t.positions(pose.skin_vertices, pose.parts))
    # lip margins separate when the jaw opens
    up = pose.template_vertices[kinds == "lip_upper"]
    lo = pose.template_vertices[kinds == "lip_lower"]
    assert up[:, 1].mean() - lo[:, 1].mean() > 0.015


def test_template_mesh_quality_and_holes(subj):
    t = subj.template
    T = np.asarray(t.triangles)
    n = t.n_vertices
    assert T.min() >= 0 and T.max() < n and len(T) > 1.5 * n
    assert len(np.unique(T)) == n                        # every vertex is used
    e = np.concatenate([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]])
    assert len(np.unique(e, axis=0)) == len(e)           # consistently oriented, manifold
    und, cnt = np.unique(np.sort(e, 1), axis=0, return_counts=True)
    assert cnt.max() == 2
    # outward: triangle normals agree with the skin's normals there
    P = t.neutral
    nrm = np.cross(P[T[:, 1]] - P[T[:, 0]], P[T[:, 2]] - P[T[:, 0]])
    cen = P[T].mean(1)
    skin_n = subj.neutral.skin_normals[cKDTree(subj.neutral_skin).query(cen)[1]]
    assert np.mean(np.einsum("ij,ij->i", nrm, skin_n) > 0) > 0.99
    # no slivers on the face (3-D angles); the extensions' stitches and hole fills: a few, none degenerate
    mn, mx = triangle_quality(P, t.face_triangles)
    assert mn.min() > 9.0 and mx.max() < 140.0
    mn, mx = triangle_quality(P, T)
    assert mn.min() > 1.0 and np.mean(mn < 9.0) < 0.01
    # the mouth and eye openings are holes: their loops are boundary edges
    boundary = {tuple(x) for x in und[cnt == 1]}
    assert set(t.holes) == {"mouth", "eye_left", "eye_right"}
    for name, loop in t.holes.items():
        loop = list(loop)
        for a, b in zip(loop, loop[1:] + loop[:1]):
            assert tuple(sorted((a, b))) in boundary, (name, a, b)
        # nothing covers the opening: the neutral opening's centre is not inside any triangle
    pose = subj.neutral
    for name in ("mouth", "eye_left", "eye_right"):
        loop = np.asarray(t.holes[name])
        assert len(loop) >= 8


def test_coarse_points_and_regions(subj):
    t = subj.template
    assert len(t.coarse_points) == 18 and len(set(t.coarse_points)) == 18
    assert list(t.coarse_names) == list(COARSE_NAMES)
    names = {nm: t.names[i] for nm, i in zip(t.coarse_names, t.coarse_points)}
    assert names["nose_tip"] == "nose_tip" and names["ear_L"] == "ear_L"
    tip = t.neutral[t.coarse_points[t.coarse_names.index("nose_tip")]]
    assert tip[2] > 0.105 and abs(tip[0]) < 0.004
    Tc = np.asarray(t.coarse_triangles)
    assert len(Tc) >= 16 and Tc.min() >= 0 and Tc.max() < 18
    # regions partition the vertices, each non-empty: the face's ten and one per extension
    ext_regions = {e["region"] for e in t.extensions.values()}
    assert set(t.regions) == set(REGION_NAMES) | ext_regions
    allr = np.concatenate([t.regions[k] for k in t.regions])
    assert len(allr) == t.n_vertices and len(np.unique(allr)) == t.n_vertices
    for k in REGION_NAMES:
        assert len(t.regions[k]) >= 5, k
    P = t.neutral
    assert P[t.regions["forehead"], 1].min() > 0.03
    assert P[t.regions["cheek_left"], 0].min() > 0 and P[t.regions["cheek_right"], 0].max() < 0
    assert P[t.regions["neck"], 1].max() < -0.08


def test_teeth_strips_and_eyes(subj):
    t = subj.template
    pose = subj.pose(subj.params(jaw_open=0.2), textures=False)
    world = t.teeth_positions(pose.transforms)
    for k in ("upper", "lower"):
        s = t.teeth[k]
        V, F = np.asarray(s["vertices"]), np.asarray(s["triangles"])
        n_teeth = len(F) // 2
        assert len(F) == 2 * n_teeth and len(V) == 2 * (n_teeth + 1) and n_teeth >= 8
        T = pose.transforms[s["part"]]
        np.testing.assert_allclose(world[k], V @ T[:3, :3].T + T[:3, 3])
        # the strip lies on the teeth: every strip vertex is within 2 mm of the rest teeth mesh
        d = cKDTree(subj.part_rest[s["part"]]).query(V)[0]
        assert d.max() < 0.003
    for name, e in t.eyes.items():
        np.testing.assert_allclose(e["centre"], subj.eye_centres[name])
        assert e["radius"] == pytest.approx(H.EYE_RADIUS)


@pytest.mark.parametrize("truth", [False, True])
def test_template_json_round_trip(subj, truth):
    t = subj.template
    text = t.to_json(include_truth=truth)
    d = json.loads(text)
    assert d["schema"] == "mifacerf.template/1"
    assert ("triangle" in d["vertices"][0]) == truth
    u = Template.from_json(text)
    assert u.kinds == t.kinds and u.names == t.names
    np.testing.assert_allclose(u.neutral, t.neutral)
    np.testing.assert_array_equal(u.triangles, t.triangles)
    np.testing.assert_array_equal(u.coarse_points, t.coarse_points)
    np.testing.assert_array_equal(u.coarse_triangles, t.coarse_triangles)
    assert u.coarse_names == t.coarse_names
    for k in t.regions:
        np.testing.assert_array_equal(u.regions[k], t.regions[k])
    for k in t.holes:
        np.testing.assert_array_equal(u.holes[k], t.holes[k])
    for k in t.teeth:
        np.testing.assert_allclose(u.teeth[k]["vertices"], t.teeth[k]["vertices"])
        np.testing.assert_array_equal(u.teeth[k]["triangles"], t.teeth[k]["triangles"])
    for k in t.eyes:
        np.testing.assert_allclose(u.eyes[k]["centre"], t.eyes[k]["centre"])
    assert u.has_truth() == truth
    if truth:
        np.testing.assert_array_equal(u.tri, t.tri)
        np.testing.assert_allclose(u.bary, t.bary)
        pose = subj.pose(subj.params(smile_R=1), textures=False)
        np.testing.assert_allclose(u.positions(pose.skin_vertices, pose.parts, subj.skin_faces),
                                   pose.template_vertices)
    else:
        with pytest.raises(ValueError):
            u.positions(subj.neutral.skin_vertices, {}, subj.skin_faces)
    with pytest.raises(ValueError):
        Template.from_json(json.dumps({**d, "schema": "something/else"}))
