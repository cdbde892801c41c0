"""Horn (1987) against scipy's Rotation.align_vectors on random and near-degenerate point sets."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from mifacerf.geometry.horn1987 import horn, horn_quaternion, quaternion_to_matrix

SET = settings(max_examples=40, deadline=None)
pytestmark = pytest.mark.filterwarnings("ignore:Optimal rotation is not uniquely:UserWarning")


def cost(R, t, P, Q, w=None):
    r = np.einsum("ab,nb->na", R, P) + t - Q
    w = np.ones(len(P)) if w is None else w
    return float(np.sum(w * np.sum(r * r, axis=1)))


def scipy_fit(P, Q, w=None):
    w = np.ones(len(P)) if w is None else w
    cp = w @ P / w.sum()
    cq = w @ Q / w.sum()
    r, _ = Rotation.align_vectors(Q - cq, P - cp, weights=w)
    R = r.as_matrix()
    return R, cq - R @ cp


def make_set(kind, rng, n=12):
    if kind == "random":
        P = rng.normal(size=(n, 3))
    elif kind == "coplanar":
        P = np.c_[rng.normal(size=(n, 2)), np.zeros(n)]
    elif kind == "nearly_coplanar":
        P = np.c_[rng.normal(size=(n, 2)), 1e-9 * rng.normal(size=n)]
    elif kind == "collinear":
        P = np.outer(rng.normal(size=n), rng.normal(size=3))
    elif kind == "three":
        P = rng.normal(size=(3, 3))
    else:
        raise ValueError(kind)
    return P


@SET
@given(seed=st.integers(0, 2 ** 31), kind=st.sampled_from(["random", "coplanar", "nearly_coplanar", "collinear", "three"]),
       log_scale=st.sampled_from([-150.0, -6.0, 0.0, 6.0, 150.0]), noise=st.sampled_from([0.0, 1e-3, 0.3]))
def test_matches_scipy_align_vectors(seed, kind, log_scale, noise):
    rng = np.random.default_rng(seed)
    s = 10.0 ** log_scale
    P = make_set(kind, rng) * s
    R0 = Rotation.random(random_state=seed % 2 ** 32).as_matrix()
    Q = P @ R0.T + rng.normal(size=3) * s + noise * s * rng.normal(size=P.shape)
    R, t = horn(P, Q)
    assert np.isclose(np.linalg.det(R), 1.0, atol=1e-12)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    Rs, ts = scipy_fit(P, Q)
    c, cs = cost(R / 1.0, t, P, Q), cost(Rs, ts, P, Q)
    # same optimum (collinear sets leave the rotation about the line free: compare costs)
    assert c <= cs * (1 + 1e-8) + 1e-20 * s * s + 1e-9 * s * s * len(P)
    if kind in ("random", "coplanar", "three") and noise < 0.1:
        assert np.allclose(R, Rs, atol=1e-7)
    if noise == 0.0 and kind != "collinear":
        assert np.allclose(R, R0, atol=1e-7)


@SET
@given(seed=st.integers(0, 2 ** 31))
def test_weighted_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    P = rng.normal(size=(9, 3))
    Q = rng.normal(size=(9, 3))
    w = rng.random(9) + 0.01
    R, t = horn(P, Q, w)
    Rs, ts = scipy_fit(P, Q, w)
    assert cost(R, t, P, Q, w) <= cost(Rs, ts, P, Q, w) * (1 + 1e-9) + 1e-12


def test_never_a_reflection():
    rng = np.random.default_rng(1)
    P = rng.normal(size=(20, 3))
    Q = P * np.array([1.0, 1.0, -1.0])           # a mirror image: Kabsch without the fix returns a reflection
    R, t = horn(P, Q)
    assert np.isclose(np.linalg.det(R), 1.0)
    Rs, ts = scipy_fit(P, Q)
    assert cost(R, t, P, Q) <= cost(Rs, ts, P, Q) * (1 + 1e-9)


def test_coincident_and_zero_weight_give_identity():
    P = np.tile([[1.0, 2.0, 3.0]], (5, 1))
    Q = np.random.default_rng(0).normal(size=(5, 3))
    R, t = horn(P, Q)
    assert np.array_equal(R, np.eye(3))
    assert np.allclose(t, Q.mean(0) - P[0])
    R, t = horn(Q, P)            # target coincident
    assert np.array_equal(R, np.eye(3))
    R, t = horn(Q, Q + 1, np.zeros(5))
    assert np.array_equal(R, np.eye(3)) and np.array_equal(t, np.zeros(3))
    # coincident up to roundoff far from the origin
    P2 = np.array([[100.0, 100.0, 100.0]] * 4) + np.array([0, 1e-14, 0, 0])[:, None]
    R, _ = horn(P2, Q[:4])
    assert np.array_equal(R, np.eye(3))


def test_single_point_and_two_points():
    R, t = horn(np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    assert np.array_equal(R, np.eye(3)) and np.allclose(t, [-1, 1, 0])
    P = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    Q = np.array([[0.0, 0, 0], [0.0, 1.0, 0]])
    R, t = horn(P, Q)
    assert np.allclose(R @ P.T + t[:, None], Q.T, atol=1e-12)


def test_batched_shapes_and_reshape_invariance():
    rng = np.random.default_rng(2)
    P = rng.normal(size=(2, 3, 7, 3))
    Q = rng.normal(size=(2, 3, 7, 3))
    R, t = horn(P, Q)
    assert R.shape == (2, 3, 3, 3) and t.shape == (2, 3, 3)
    R2, t2 = horn(P.reshape(6, 7, 3), Q.reshape(6, 7, 3))
    assert np.allclose(R.reshape(6, 3, 3), R2, atol=1e-14) and np.allclose(t.reshape(6, 3), t2, atol=1e-14)
    R3, _ = horn(P[1, 2], Q[1, 2])
    assert np.allclose(R[1, 2], R3, atol=1e-14)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_raises(bad):
    P = np.zeros((4, 3))
    P[2, 1] = bad
    with pytest.raises(ValueError, match="non-finite"):
        horn(P, np.ones((4, 3)))


def test_shape_errors():
    with pytest.raises(ValueError, match=r"\(\.\.\., N, 3\)"):
        horn(np.zeros((4, 2)), np.zeros((4, 2)))
    with pytest.raises(ValueError):
        horn(np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="non-negative"):
        horn(np.zeros((4, 3)), np.zeros((4, 3)), -np.ones(4))


def test_quaternion_convention():
    q, _ = horn_quaternion(np.eye(3), np.eye(3)[[1, 0, 2]] * [[-1], [1], [1]])
    assert q[0] >= 0
    # 90 degrees about z: x -> y, y -> -x
    R = quaternion_to_matrix(np.array([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]))
    assert np.allclose(R @ [1, 0, 0], [0, 1, 0]) and np.allclose(R @ [0, 1, 0], [-1, 0, 0])


@pytest.mark.parametrize("precision,tol", [("float64", 1e-10), ("float32", 2e-5)])
def test_drjit_kernel_horn_matches_numpy(precision, tol):
    from mifacerf.blending.weights import horn_rotations

    rng = np.random.default_rng(3)
    P = rng.normal(size=(200, 10, 3))
    R0 = Rotation.random(200, random_state=4).as_matrix()
    Q = np.einsum("nab,nkb->nka", R0, P) + 0.05 * rng.normal(size=P.shape)
    P[:20, :, 2] = 0.0                         # coplanar
    P[20:30] = P[20:30, :1] * np.ones((1, 10, 1)) * 1.0   # coincident → identity
    Q[:20] = np.einsum("nab,nkb->nka", R0[:20], P[:20])
    R, _ = horn(P, Q)
    Rk = horn_rotations(P, Q, precision=precision)
    assert np.allclose(np.linalg.det(Rk), 1.0, atol=10 * tol)
    assert np.abs(Rk - R).max() < tol
