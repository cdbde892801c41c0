"""The coarse-mesh morph, MLS placement and the reference choice against analytic deformations."""
import numpy as np
import pytest
from scipy.spatial import Delaunay
from scipy.spatial.transform import Rotation

from mifacerf.geometry.schaefer2006 import mls_affine
from mifacerf.registration.morph import (CoarseMorph, choose_references, coarse_neighbourhoods,
                                         deformation_distances, point_triangle_distance)


@pytest.fixture(scope="module")
def cap():
    """A coarse mesh on a spherical cap (like the 18 coarse points over a face)."""
    th, ph = np.meshgrid(np.linspace(-0.8, 0.8, 5), np.linspace(-0.6, 0.6, 4))
    P = np.stack([0.1 * np.sin(th.ravel()) * np.cos(ph.ravel()), 0.1 * np.sin(ph.ravel()),
                  0.1 * np.cos(th.ravel()) * np.cos(ph.ravel())], 1)
    F = Delaunay(np.stack([th.ravel(), ph.ravel()], 1)).simplices
    return P, F


def random_rigid(rng):
    return Rotation.from_rotvec(rng.normal(0, 0.3, 3)).as_matrix(), rng.normal(0, 0.02, 3)


def test_coarse_morph_reproduces_rigid_motions(cap, rng):
    P, F = cap
    pts = rng.normal(0, 0.04, (200, 3)) + [0, 0, 0.1]
    for _ in range(3):
        R, t = random_rigid(rng)
        m = CoarseMorph(P, P @ R.T + t, F)
        np.testing.assert_allclose(m(pts), pts @ R.T + t, atol=1e-12)


def test_coarse_morph_carries_planar_affine_maps(rng):
    th, ph = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 4))
    P = np.stack([0.05 * th.ravel(), 0.05 * ph.ravel(), np.zeros(th.size)], 1)
    F = Delaunay(P[:, :2]).simplices
    A = np.array([[1.2, 0.3, 0], [-0.1, 0.8, 0], [0, 0, 1]])
    t = np.array([0.01, -0.02, 0.003])
    pts = np.concatenate([rng.uniform(-0.05, 0.05, (100, 2)), np.zeros((100, 1))], 1)
    m = CoarseMorph(P, P @ A.T + t, F)
    np.testing.assert_allclose(m(pts), pts @ A.T + t, atol=1e-12)
    # a point off the plane keeps its (absolute) height above the morphed plane, as in BN92
    off = np.array([[0.0, 0.0, 0.004]])
    np.testing.assert_allclose(m(off)[0, 2], 0.004 + t[2], atol=1e-12)


def test_coarse_morph_is_smooth_and_local(cap, rng):
    P, F = cap
    Q = P.copy()
    Q[0] += [0.0, 0.0, 0.01]          # move one coarse point
    m = CoarseMorph(P, Q, F)
    near = P[0] + [0.001, 0.001, 0.0]
    far = P[-1] + [0.001, 0.001, 0.0]
    d_near = np.linalg.norm(m(near[None])[0] - near)
    d_far = np.linalg.norm(m(far[None])[0] - far)
    assert d_near > 0.003 and d_far < 0.1 * d_near
    # continuity: nearby points morph to nearby points
    a = rng.normal(0, 0.03, (50, 3)) + [0, 0, 0.1]
    assert np.max(np.linalg.norm(m(a + 1e-6) - m(a), axis=1)) < 1e-4


def test_coarse_morph_ignores_missing_coarse_points(cap, rng):
    P, F = cap
    R, t = random_rigid(rng)
    Q = P @ R.T + t
    Q[3] = np.nan
    m = CoarseMorph(P, Q, F)
    pts = rng.normal(0, 0.03, (20, 3)) + [0, 0, 0.1]
    np.testing.assert_allclose(m(pts), pts @ R.T + t, atol=1e-12)
    with pytest.raises(ValueError):
        CoarseMorph(P, np.full_like(P, np.nan), F)


def test_point_triangle_distance_matches_brute_force(cap, rng):
    P, F = cap
    pts = rng.normal(0, 0.05, (12, 3)) + [0, 0, 0.1]
    d = point_triangle_distance(pts, P[F[:, 0]], P[F[:, 1]], P[F[:, 2]])
    u = rng.random((6000, 2))
    u[u.sum(1) > 1] = 1 - u[u.sum(1) > 1]
    S = P[F[:, 0]][:, None] + u[None, :, :1] * (P[F[:, 1]] - P[F[:, 0]])[:, None] \
        + u[None, :, 1:] * (P[F[:, 2]] - P[F[:, 0]])[:, None]
    brute = np.linalg.norm(pts[:, None, None] - S[None], axis=-1).min(-1)
    assert np.all(d <= brute + 1e-12) and np.all(brute - d < 1e-3)


def test_mls_affine_exact_for_rigid_and_affine(cap, rng):
    P, _ = cap
    pts = P[:5] + rng.normal(0, 0.003, (5, 3))
    R, t = random_rigid(rng)
    np.testing.assert_allclose(mls_affine(P, P @ R.T + t, pts), pts @ R.T + t, atol=1e-12)
    A = np.eye(3) + rng.normal(0, 0.1, (3, 3))
    np.testing.assert_allclose(mls_affine(P, P @ A.T + t, pts, reg=1e-8), pts @ A.T + t, atol=1e-7)


def test_reference_choice_follows_local_similarity(cap):
    P, F = cap
    nb = coarse_neighbourhoods(len(P), F)
    N = P.copy()
    left = P[:, 0] < -0.02
    N[left] += [0.0, 0.0, 0.01] * (P[left, :1] / 0.1) ** 2   # the new expression bends its left side
    A = P.copy()                                             # reference 0: the neutral
    B = P.copy()
    B[left] = N[left]                                        # reference 1: bends the left side too,
    B[~left] += [0.0, 0.004, 0.0] * (P[~left, :1] / 0.1)     # ... but shears the right side
    assert np.nanmax(deformation_distances(P, A, P @ Rotation.from_rotvec([0, .2, 0]).as_matrix().T, nb)) < 1e-12
    D = np.stack([deformation_distances(P, A, N, nb), deformation_distances(P, B, N, nb)])
    pts = np.array([P[left][0] * 1.01, P[P[:, 0] > 0.05][0] * 1.01])
    assert choose_references(pts, P, D, sigma=0.01).tolist() == [1, 0]
