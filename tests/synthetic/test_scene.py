"""The subject's Mitsuba scene: in-place pose updates, per-hit classification, eyelids, mouth."""
import time

import numpy as np
import pytest

from mifacerf.synthetic import PART_IDS, SubjectScene, default_subject
from mifacerf.synthetic import head as H


@pytest.fixture(scope="module")
def subj():
    return default_subject()


@pytest.fixture(scope="module")
def scene(subj, mi):
    return SubjectScene(subj)


def _cast(mi, scene, origins, dirs):
    o = np.asarray(origins, np.float32)
    d = np.asarray(dirs, np.float32)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    rays = mi.Ray3f(mi.Point3f(o.T), mi.Vector3f(d.T))
    si = scene.scene.ray_intersect(rays)
    pid, face = scene.classify(si)
    n = np.array(si.n).T
    return np.array(pid), np.array(face), np.array(si.t), n, d


def _rays_at_eye(subj, pose, name, n=200, cone=0.5):
    """Rays from 30 cm in front aimed at points of the eyeball's front cap."""
    T = pose.parts[name].transform
    c = T[:3, :3] @ subj.eye_centres[name] + T[:3, 3]
    rng = np.random.default_rng(0)
    th = cone * np.sqrt(rng.random(n))
    ph = rng.random(n) * 2 * np.pi
    local = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
    targets = c + H.EYE_RADIUS * local @ T[:3, :3].T
    origins = targets + np.array([0.0, 0.0, 0.3])
    return origins, targets - origins


def test_all_bsdfs_are_non_delta(scene, mi):
    for shape in scene.scene.shapes():
        f = shape.bsdf().flags()
        assert not (f & mi.BSDFFlags.Delta), shape.id()
        assert f & (mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.GlossyReflection)


def test_classify_parts_and_face_region(subj, scene, mi):
    scene.set_pose(subj.neutral)
    tip = subj.neutral.skin_vertices[np.argmax(subj.neutral.skin_vertices[:, 2])]
    eye = subj.eye_centres["eye_left"] + [0, 0, 0.02]
    origins = [tip + [0, 0, 0.3], eye + [0, 0, 0.3], [0.5, 0.5, 0.5], [0.0, 0.11, 0.3], [0.09, 0.0, -0.3]]
    targets = [tip, eye, [0.5, 0.5, 0.4], [0.0, 0.11, -0.01], [0.0, 0.0, -0.05]]
    pid, face, t, _, _ = _cast(mi, scene, origins, np.subtract(targets, origins))
    assert pid[0] == PART_IDS["skin"] and face[0]           # nose tip: skin, in the face region
    assert pid[1] == PART_IDS["eye_left"] and not face[1]
    assert pid[2] == 0 and not face[2]                       # a miss
    assert pid[3] == PART_IDS["skin"] and not face[3]        # top of the head (hair), outside the face
    assert pid[4] == PART_IDS["skin"] and not face[4]        # back of the head
    for name, shape in scene.shapes.items():
        assert scene.part_of(shape) == name


def test_set_pose_moves_the_surface(subj, scene, mi):
    o = [[0.0, -0.10, 0.4]]
    d = [[0.0, 0.0, -1.0]]
    scene.set_pose(subj.neutral)
    _, _, t0, _, _ = _cast(mi, scene, o, d)
    scene.set_pose(subj.pose(subj.params(jaw_open=0.3)))
    _, _, t1, _, _ = _cast(mi, scene, o, d)
    assert abs(t1[0] - t0[0]) > 0.003
    scene.set_pose(subj.neutral)
    _, _, t2, _, _ = _cast(mi, scene, o, d)
    assert t2[0] == pytest.approx(t0[0], abs=1e-5)
    pose = subj.pose(subj.params(smile_L=1, brow_raise_L=1))
    t = time.perf_counter()
    scene.set_pose(pose)
    assert time.perf_counter() - t < 2.0


def test_open_eyes_show_the_eyeball_and_shut_lids_cover_it(subj, scene, mi):
    pose = subj.neutral
    scene.set_pose(pose)
    for name in ("eye_left", "eye_right"):
        o, d = _rays_at_eye(subj, pose, name, cone=0.25)
        pid, *_ = _cast(mi, scene, o, d)
        assert np.mean(pid == PART_IDS[name]) > 0.9        # iris and cornea visible
    pose = subj.pose(subj.params(blink_L=1, blink_R=1, gaze_yaw=0.3, gaze_pitch=0.2))
    scene.set_pose(pose)
    for name in ("eye_left", "eye_right"):
        o, d = _rays_at_eye(subj, pose, name, n=600, cone=1.2)
        pid, *_ = _cast(mi, scene, o, d)
        assert np.all(pid == PART_IDS["skin"]), np.unique(pid, return_counts=True)
    scene.set_pose(subj.neutral)


def test_open_mouth_shows_teeth_and_a_dark_interior_never_the_head_inside(subj, scene, mi):
    pose = subj.pose(subj.params(jaw_open=0.3, upper_lip_raise=0.5, lower_lip_down=0.5))
    scene.set_pose(pose)
    ms = subj.grid.slits["mouth"]
    V = pose.skin_vertices
    # rays from a frontal camera through points between the lip margins
    mid = 0.5 * (V[ms.upper] + V[ms.lower])
    rng = np.random.default_rng(1)
    pts = []
    for k in range(len(ms.upper)):
        for s in rng.random(6):
            pts.append(V[ms.lower[k]] + s * (V[ms.upper[k]] - V[ms.lower[k]]))
    pts = np.array(pts)
    cam = np.array([0.0, -0.05, 0.6])
    pid, face, t, n, d = _cast(mi, scene, np.tile(cam, (len(pts), 1)), pts - cam)
    assert np.all(pid > 0)
    inner = {PART_IDS["teeth_upper"], PART_IDS["teeth_lower"], PART_IDS["mouth_interior"]}
    assert np.mean([p in inner for p in pid]) > 0.5
    assert (pid == PART_IDS["teeth_upper"]).any() and (pid == PART_IDS["teeth_lower"]).any()
    # skin hits (lip margins) are seen from outside, never the back of the head's skin
    sk = pid == PART_IDS["skin"]
    assert np.all(np.einsum("ij,ij->i", n[sk], d[sk]) < 0)
    scene.set_pose(subj.neutral)


def test_extra_scene_entries(subj, mi):
    sc = SubjectScene(subj, extra={"env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}})
    assert len(sc.scene.emitters()) == 1
