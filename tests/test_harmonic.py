"""mifacerf.geometry.harmonic: membrane and thin-plate interpolation over a mesh's edge graph.

Oracles: linear functions (reproduced exactly by the membrane on a regular grid with its border known;
continued past the known vertices by the thin plate), the 1-D chain's closed form, the maximum
principle, and a dense least-squares solve of the thin-plate energy.
"""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from mifacerf.geometry.harmonic import harmonic_interpolation


def grid(nx: int, ny: int):
    """A regular triangulated nx × ny grid: (positions (N, 2), faces (F, 3))."""
    x, y = np.meshgrid(np.arange(nx, dtype=float), np.arange(ny, dtype=float), indexing="ij")
    P = np.stack([x.ravel(), y.ravel()], 1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return P, F


def linear(P):
    return np.stack([0.3 * P[:, 0] - 0.7 * P[:, 1] + 2.0, -1.1 * P[:, 0] + 0.2 * P[:, 1]], 1)


def test_membrane_reproduces_a_linear_function_from_the_border():
    P, F = grid(9, 7)
    border = np.flatnonzero((P[:, 0] == 0) | (P[:, 0] == 8) | (P[:, 1] == 0) | (P[:, 1] == 6))
    f = linear(P)
    out = harmonic_interpolation(len(P), F, border, f[border], order=1)
    assert out.shape == (len(P), 2)
    np.testing.assert_allclose(out, f, atol=1e-9)


def test_chain_is_linear_between_its_known_ends():
    # a path graph (degenerate triangles i, i+1, i+1): the membrane is linear between the known ends,
    # and the known values may come in any order
    F = np.stack([np.arange(10), np.arange(1, 11), np.arange(1, 11)], 1)
    out = harmonic_interpolation(11, F, [10, 0], [6.0, 1.0], order=1)
    assert out.shape == (11,)
    np.testing.assert_allclose(out, 1.0 + 0.5 * np.arange(11), atol=1e-9)


def test_thin_plate_continues_a_trend_the_membrane_flattens():
    # known: the left half of a strip, a linear ramp; the right half is free
    P, F = grid(20, 4)
    known = np.flatnonzero(P[:, 0] <= 9)
    f = 0.5 * P[:, 0]
    free = P[:, 0] > 9
    o1 = harmonic_interpolation(len(P), F, known, f[known], order=1)
    o2 = harmonic_interpolation(len(P), F, known, f[known], order=2)
    np.testing.assert_allclose(o1[free], 4.5, atol=1e-9)        # the membrane: the last known value
    e1 = np.abs(o1[free] - f[free]).mean()
    e2 = np.abs(o2[free] - f[free]).mean()
    assert e2 < 0.6 * e1, (e1, e2)
    assert (np.diff(o2.reshape(20, 4)[10:, 1]) > 0).all()       # it keeps rising past the known half


def test_thin_plate_matches_a_dense_least_squares_solve():
    rng = np.random.default_rng(3)
    P, F = grid(6, 5)
    n = len(P)
    known = rng.choice(n, 9, replace=False)
    vals = rng.normal(size=(9, 3))
    out = harmonic_interpolation(n, F, known, vals, order=2)
    A = np.zeros((n, n))
    for a, b in np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]):
        A[a, b] = A[b, a] = 1.0
    L = np.diag(A.sum(1)) - A
    free = np.setdiff1d(np.arange(n), known)
    # min |L x|² with x[known] = vals: least squares in the free unknowns
    sol, *_ = np.linalg.lstsq(L[:, free], -L[:, known] @ vals, rcond=None)
    np.testing.assert_allclose(out[free], sol, atol=1e-8)
    np.testing.assert_allclose(out[known], vals)


def test_values_do_not_cross_a_hole():
    # a U: two arms (columns 0-1 and 3-4) joined at the bottom; the arms' tips are 2 apart in space
    # but far apart along the mesh
    P, F = grid(5, 12)
    keep = ~((P[:, 0] == 2) & (P[:, 1] >= 2))                   # cut the middle column above the base
    Fk = F[keep[F].all(1)]
    tip = lambda x: np.flatnonzero((P[:, 0] == x) & (P[:, 1] == 11))[0]
    out = harmonic_interpolation(len(P), Fk, [tip(1), tip(3)], [0.0, 10.0], order=1)
    near = lambda x: out[np.flatnonzero((P[:, 0] == x) & (P[:, 1] == 10))[0]]
    assert near(1) < 2.0 and near(3) > 8.0, (near(1), near(3))
    # the same two points joined straight across (no hole): the vertex between them is about half way
    # (the diagonals of the triangulation break the symmetry a little)
    full = harmonic_interpolation(len(P), F, [tip(1), tip(3)], [0.0, 10.0], order=1)
    assert abs(full[np.flatnonzero((P[:, 0] == 2) & (P[:, 1] == 11))[0]] - 5.0) < 0.2


def test_degenerate_inputs_are_finite_and_documented():
    P, F = grid(4, 4)
    F2 = np.concatenate([F, F + 16])                              # a second copy with no known vertex
    n = 16 * 2 + 1                                                # and one vertex in no triangle
    out = harmonic_interpolation(n, F2, [0], [[2.0, -1.0]], order=2, fill=0.0)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[:16], [[2.0, -1.0]] * 16)      # one known value: constant
    np.testing.assert_allclose(out[16:], 0.0)                     # unanchored component, loose vertex: fill
    # nothing free: the known values as given
    np.testing.assert_allclose(harmonic_interpolation(3, [[0, 1, 2]], [0, 1, 2], [1.0, 2.0, 3.0]), [1, 2, 3])


@pytest.mark.parametrize("bad, match", [
    (dict(known_ids=[0, 0], values=[1.0, 2.0]), "repeat"),
    (dict(known_ids=[0, 1], values=[1.0]), "shape"),
    (dict(known_ids=[0, 1], values=[1.0, np.nan]), "finite"),
    (dict(known_ids=[0, 1], values=[1.0, 2.0], order=3), "order"),
])
def test_bad_input_names_the_problem(bad, match):
    with pytest.raises(ValueError, match=match):
        harmonic_interpolation(3, [[0, 1, 2]], **bad)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), k=st.integers(1, 20))
def test_membrane_obeys_the_maximum_principle(seed, k):
    rng = np.random.default_rng(seed)
    P, F = grid(6, 6)
    known = rng.choice(len(P), k, replace=False)
    vals = rng.uniform(-5, 5, k)
    out = harmonic_interpolation(len(P), F, known, vals, order=1)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out[known], vals)
    assert out.min() >= vals.min() - 1e-9 and out.max() <= vals.max() + 1e-9
