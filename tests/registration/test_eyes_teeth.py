"""Head pose, teeth and eye centres against analytic poses."""
import numpy as np
from scipy.spatial.transform import Rotation

from mifacerf.geometry.rigid import apply, homogeneous, rigid_from_points, robust_rigid
from mifacerf.registration import eyes_teeth as ET
from mifacerf.rig import CAMERA_LAYOUTS, camera_ring
from mifacerf.synthetic.hand_inputs import iris_circle

EARS_NOSE = np.array([[0.075, -0.005, -0.01], [-0.075, -0.005, -0.01], [0.0, 0.007, 0.09]])


def pose(rotvec, t):
    return homogeneous(Rotation.from_rotvec(rotvec).as_matrix(), np.asarray(t, float))


def test_head_pose_from_three_points_and_refinement(rng):
    T = pose([0.1, -0.3, 0.05], [0.01, -0.02, 0.005])
    Q = apply(T, EARS_NOSE)
    np.testing.assert_allclose(rigid_from_points(EARS_NOSE, Q), T, atol=1e-12)
    # noisy marks, refined with rigid fiducials (and a few that moved non-rigidly)
    Qn = Q + rng.normal(0, 0.0015, Q.shape)
    T3 = rigid_from_points(EARS_NOSE, Qn)
    Pr = rng.normal(0, 0.04, (40, 3)) + [0, 0.04, 0.08]
    Qr = apply(T, Pr) + rng.normal(0, 0.0003, Pr.shape)
    Qr[:8] += [0.0, 0.006, 0.0]                   # raised brows do not move with the skull
    Tr, used = ET.refine_rigid(T3, EARS_NOSE, Qn, Pr, Qr, 0.001)
    angle = lambda A: np.degrees(np.arccos(np.clip((np.trace(A[:3, :3].T @ T[:3, :3]) - 1) / 2, -1, 1)))
    assert angle(Tr) < 0.5 * angle(T3) and 30 <= used <= 33


def test_robust_rigid_ignores_deforming_points(rng):
    T = pose([0.0, 0.2, 0.0], [0.0, 0.0, 0.01])
    P = rng.normal(0, 0.05, (60, 3))
    Q = apply(T, P)
    Q[:25] += rng.normal(0, 0.01, (25, 3))
    np.testing.assert_allclose(robust_rigid(P, Q), T, atol=1e-9)


def test_lower_teeth_from_one_mark():
    T_head = pose([0.0, 0.1, 0.0], [0.0, 0.0, 0.0])
    mark_n = np.array([0.0, -0.07, 0.07])
    mark_e = apply(T_head, mark_n[None])[0] + [0.0, -0.008, 0.0]    # jaw dropped 8 mm
    T_lo = ET.lower_teeth_transform(T_head, mark_n, mark_e)
    np.testing.assert_allclose(apply(T_lo, mark_n[None])[0], mark_e, atol=1e-12)
    np.testing.assert_allclose(T_lo[:3, :3], T_head[:3, :3])


def test_eye_centre_from_iris_marks(rng):
    cams = camera_ring(CAMERA_LAYOUTS[6], width=256, height=256, seed=1)
    centre = np.array([0.0315, 0.0055, 0.0655])
    depth, r_iris = 0.0104, 0.0059
    T_head = pose([0.0, 0.25, 0.0], [0.0, 0.0, 0.0])
    c_w = apply(T_head, centre[None])[0]
    g = T_head[:3, :3] @ [0, 0, 1.0]
    circ = iris_circle(c_w + depth * g, g, r_iris, 32)
    views = {cam.name: cam.project(circ)[0] + rng.normal(0, 0.3, (32, 2)) for cam in cams[:3]}
    ic = ET.iris_centre(cams, views)
    assert np.linalg.norm(ic - (c_w + depth * g)) < 5e-4
    d = ET.gaze_direction("forward", T_head, ic, cams)
    np.testing.assert_allclose(d, g, atol=1e-12)
    assert np.linalg.norm(ic - depth * d - c_w) < 5e-4
    assert ET.eye_depth({"radius": 0.012, "iris_radius": 0.0059}) == np.sqrt(0.012 ** 2 - 0.0059 ** 2)
    assert ET.gaze_direction("nonexistent-camera", T_head, ic, cams) is None
