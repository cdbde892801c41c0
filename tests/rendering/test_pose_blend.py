"""Blends that turn the head: faces blended in their head frames, head poses as rigid motions (issue 16)."""
import numpy as np

from mifacerf.rendering.pose_blend import blend_geometry, blend_motions


def _turn(deg, pivot):
    a = np.radians(deg)
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, pivot - R @ pivot
    return T


def test_a_blend_of_turns_about_one_pivot_is_the_turn_by_the_blended_angle():
    pivot = np.array([0.0, -0.12, -0.02])
    T = blend_motions(np.stack([np.eye(4), _turn(30, pivot)]), np.array([0.57, 0.43]))
    np.testing.assert_allclose(T, _turn(0.43 * 30, pivot), atol=1e-12)


def test_blend_geometry_turns_the_head_along_the_arc_not_the_chord():
    rng = np.random.default_rng(0)
    face = rng.normal(0, 0.05, (50, 3))
    pivot = np.array([0.0, -0.12, -0.02])
    H = np.stack([np.eye(4), _turn(30, pivot)])
    V = np.stack([face, face @ H[1, :3, :3].T + H[1, :3, 3]])
    out, Hb = blend_geometry(V, H, {0: 0.57, 1: 0.43})
    want = face @ _turn(12.9, pivot)[:3, :3].T + _turn(12.9, pivot)[:3, 3]
    np.testing.assert_allclose(out, want, atol=1e-12)
    chord = 0.57 * V[0] + 0.43 * V[1]
    assert np.linalg.norm(chord - want, axis=1).max() > 1e-3      # the linear blend is mm off the arc


def test_one_expression_is_its_registered_vertices_and_weights_are_normalised():
    rng = np.random.default_rng(1)
    V = rng.normal(0, 0.05, (3, 20, 3))
    H = np.stack([np.eye(4), _turn(10, np.zeros(3)), _turn(-20, np.ones(3) * 0.01)])
    out, Hb = blend_geometry(V, H, {2: 1.0})
    assert (out == V[2]).all() and (Hb == H[2]).all()
    a, _ = blend_geometry(V, H, {0: 1.0, 1: 1.0})
    b, _ = blend_geometry(V, H, {0: 0.5, 1: 0.5})
    np.testing.assert_allclose(a, b, atol=1e-15)
