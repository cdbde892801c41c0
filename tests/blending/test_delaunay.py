"""m-D triangulation, barycentrics and the out-of-hull rule, with their degenerate cases."""
import numpy as np
import pytest
from hypothesis import example, given, settings, strategies as st
from scipy.spatial import Delaunay, QhullError

from mifacerf.blending import delaunay as D
from mifacerf.blending.delaunay import triangulate, weights_numpy

SET = settings(max_examples=40, deadline=None)


def ghost_thickness(tri) -> float:
    """The largest altitude (a vertex's distance from the plane of the opposite face) of the triangulation's
    ghost (sliver) simplices: how far the convex hull can stand out of the non-ghost boundary; 0 without ghosts."""
    out = 0.0
    for simplex in tri.simplices[tri.ghost]:
        V = tri.points[simplex]
        alt = []
        for i in range(len(V)):
            rest = np.delete(V, i, axis=0)
            A = (rest[1:] - rest[0]).T
            c = np.linalg.lstsq(A, V[i] - rest[0], rcond=None)[0] if A.size else np.zeros(0)
            alt.append(np.linalg.norm(V[i] - rest[0] - (A @ c if A.size else 0)))
        out = max(out, max(alt))
    return out


def reconstruct(tri, ids, w):
    pos = {int(i): p for i, p in zip(tri.point_ids, tri.points)}
    return np.einsum("qk,qkm->qm", w, np.array([[pos[int(i)] for i in row] for row in ids]))


def test_intervals_m1():
    tri = triangulate(np.array([[3.0], [0.0], [1.0]]), ids=[10, 11, 12])
    assert tri.m == 1 and tri.method == "intervals"
    ids, w = weights_numpy(tri, np.array([[2.0], [0.25], [-1.0], [5.0], [1.0]]))
    d = []
    for i, x in zip(ids, w):
        acc = {}
        for a, b in zip(i.tolist(), x.tolist()):
            acc[a] = acc.get(a, 0.0) + b
        d.append({a: b for a, b in acc.items() if b > 0})
    assert d[0] == pytest.approx({12: 0.5, 10: 0.5})
    assert d[1][11] == pytest.approx(0.75) and d[1][12] == pytest.approx(0.25)
    assert d[2][11] == pytest.approx(1.0)                # clamped to the hull's end
    assert d[3][10] == pytest.approx(1.0)
    assert d[4][12] == pytest.approx(1.0)                # a source reproduces itself


def test_triangle_m2_barycentrics_and_outside():
    P = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    tri = triangulate(P)
    assert tri.m == 2 and tri.n_simplices == 1 and tri.facets.shape == (3, 2)
    ids, w = weights_numpy(tri, np.array([[0.2, 0.3], [1.0, 1.0], [-1.0, -2.0], [2.0, -0.5]]))
    dw = np.zeros((4, 3))
    np.add.at(dw, (np.arange(4)[:, None], ids), w)
    assert np.allclose(dw[0], [0.5, 0.2, 0.3])
    assert np.allclose(dw[1], [0.0, 0.5, 0.5])          # nearest hull point (0.5, 0.5)
    assert np.allclose(dw[2], [1.0, 0.0, 0.0])          # nearest hull point: the vertex (0, 0)
    assert np.allclose(dw[3], [0.0, 1.0, 0.0])


def test_tetrahedron_m3_known_barycentrics():
    P = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    tri = triangulate(P)
    ids, w = weights_numpy(tri, np.array([[0.1, 0.2, 0.3], [1.0, 1.0, 1.0]]))
    dw = np.zeros((2, 4))
    np.add.at(dw, (np.arange(2)[:, None], ids), w)
    assert np.allclose(dw[0], [0.4, 0.1, 0.2, 0.3])
    assert np.allclose(dw[1], [0, 1 / 3, 1 / 3, 1 / 3])


def test_cospherical_lattice_uses_regular_triangulation():
    g = np.stack(np.meshgrid(*[np.arange(3.0)] * 3), -1).reshape(-1, 3)
    with pytest.raises(AssertionError):                   # qhull's own result has flat simplices
        d = Delaunay(g)
        assert not np.isnan(d.transform).any()
    tri = triangulate(g)
    assert tri.m == 3 and tri.method == "regular"
    _, ratio = D.simplex_transforms(tri.points, tri.simplices)
    assert ratio.min() > 1e-3
    A = tri.points[tri.simplices[:, :3]] - tri.points[tri.simplices[:, 3:]]
    assert np.isclose(np.abs(np.linalg.det(A)).sum() / 6, 8.0)
    ids, w = weights_numpy(tri, g)                      # every lattice point reproduces itself
    assert np.allclose(w.max(axis=1), 1.0) and np.all(ids[np.arange(len(g)), w.argmax(1)] == np.arange(len(g)))


def test_duplicates_merge_to_preferred():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(8, 2))
    X = np.vstack([P, P[3:4] + 1e-12, P[5:6]])            # ids 8 and 9 duplicate 3 and 5
    tri = triangulate(X, ids=np.arange(10), preferred=9)
    assert tri.points.shape[0] == 8
    assert 9 in tri.point_ids and 5 not in tri.point_ids  # the preferred id represents its cluster
    assert 3 in tri.point_ids and 8 not in tri.point_ids  # otherwise the smallest id
    ids, w = weights_numpy(tri, X[[8]])
    assert ids[0, w[0].argmax()] == 3 and np.isclose(w[0].max(), 1.0)


def test_all_identical_gives_point():
    tri = triangulate(np.zeros((6, 3)), ids=np.arange(6) + 4, preferred=7)
    assert tri.m == 0 and tri.method.startswith("point") and list(tri.point_ids) == [7]
    ids, w = weights_numpy(tri, np.zeros((2, 0)))
    assert np.all(ids == 7) and np.all(w == 1)


def test_coplanar_in_3d_degrades_to_2d():
    rng = np.random.default_rng(1)
    P = np.c_[rng.normal(size=(10, 2)), np.zeros(10)]
    tri = triangulate(P)
    assert tri.m == 2 and "degraded from m=3" in tri.method


def test_qhull_precision_error_is_caught():
    rng = np.random.default_rng(2)
    P = np.c_[rng.normal(size=(12, 2)), 1e-15 * rng.normal(size=12)]
    with pytest.raises(QhullError, match="Initial simplex is flat"):
        Delaunay(P)                                       # the input does defeat plain qhull
    tri = triangulate(P)
    assert tri.m == 2 and np.all(np.isfinite(tri.transform))
    ids, w = weights_numpy(tri, rng.normal(size=(20, 2)))
    assert np.all(np.isfinite(w)) and np.allclose(w.sum(1), 1)


def test_boundary_sliver_becomes_a_ghost():
    P = np.array([(0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 1e-9), (0.5, 0.5, 1)], float)
    d = Delaunay(P)
    assert D.simplex_transforms(P, d.simplices)[1].min() < 1e-8      # qhull keeps a flat tetrahedron
    tri = triangulate(P)
    assert tri.method == "delaunay" and tri.n_simplices == 3 and tri.ghost.sum() == 1
    assert D.simplex_transforms(tri.points, tri.simplices[~tri.ghost])[1].min() > 0.1
    assert set(np.unique(tri.simplices[~tri.ghost])) == set(range(5))
    ids, w = weights_numpy(tri, P)                                    # all points reproduce
    assert np.all(ids[np.arange(5), w.argmax(1)] == np.arange(5)) and np.allclose(w.max(1), 1)
    # a target inside the ghost gets the weights of the nearest point of the non-ghost boundary:
    # near the base's centre, that is the diagonal shared by the two real tetrahedra's bases
    x = np.array([[0.5, 0.5, 0.3e-9]])
    g = d.find_simplex(x)[0]
    assert tri.ghost[g]
    ids, w = weights_numpy(tri, x)
    dw = np.zeros(5)
    np.add.at(dw, ids[0], w[0])
    assert np.isclose(dw[4], 0, atol=1e-6) and np.isclose(dw.sum(), 1) and (dw[1] > 0.4 or dw[0] > 0.4)


def test_errors():
    with pytest.raises(ValueError):
        triangulate(np.zeros((3, 4)))
    with pytest.raises(ValueError):
        triangulate(np.array([[np.nan, 0.0]]))


points_strategy = st.tuples(st.integers(0, 2 ** 31), st.integers(1, 3), st.integers(2, 25),
                            st.sampled_from(["gauss", "lattice", "dups", "flat"]))


def make_points(seed, m, n, kind):
    rng = np.random.default_rng(seed)
    if kind == "lattice":
        P = rng.integers(0, 3, size=(n, m)).astype(float)
    elif kind == "dups":
        P = rng.normal(size=(n, m))
        P[n // 2:] = P[: n - n // 2]
    elif kind == "flat":
        P = rng.normal(size=(n, m))
        P[:, -1] *= 1e-13
    else:
        P = rng.normal(size=(n, m))
    return P, rng


@SET
@given(points_strategy)
@example((1731, 3, 23, "gauss"))   # a ghost sliver: the projection is onto a boundary slightly inside the hull
def test_weights_properties(args):
    seed, m, n, kind = args
    P, rng = make_points(seed, m, n, kind)
    tri = triangulate(P)
    X = rng.normal(size=(60, m)) * rng.choice([0.3, 1.0, 3.0], size=(60, 1))
    X = X[:, : tri.m]
    ids, w = weights_numpy(tri, X)
    assert np.all(np.isfinite(w)) and np.all(w >= 0) and np.allclose(w.sum(1), 1, atol=1e-12)
    assert np.all(np.isin(ids, tri.point_ids))
    if tri.m == 0:
        return
    Y = reconstruct(tri, ids, w)
    # inside: the weights reproduce the point; outside: Y is the projection onto the hull
    # (x - y) . (p - y) <= 0 for every point p of the hull — onto the boundary of the non-ghost simplices,
    # which differs from the convex hull by at most the ghost slivers' thickness (module docstring, 4b)
    Pm = tri.points
    g = np.einsum("qm,pqm->pq", X - Y, Pm[:, None, :] - Y[None])
    scale = 1 + np.abs(X).max()
    slack = np.linalg.norm(X - Y, axis=1) * ghost_thickness(tri)
    assert np.all(g <= 1e-7 * scale ** 2 + slack[None])
    # every source reproduces itself (up to merged duplicates)
    ids, w = weights_numpy(tri, tri.points)
    assert np.allclose(w.max(1), 1, atol=1e-9)
    assert np.all(ids[np.arange(len(tri.points)), w.argmax(1)] == tri.point_ids)


@SET
@given(points_strategy)
@example((275329197, 3, 24, "flat"))   # qhull kept its point at infinity in a simplex (found by a clean-clone run)
def test_weights_are_continuous(args):
    seed, m, n, kind = args
    P, rng = make_points(seed, m, n, kind)
    tri = triangulate(P)
    if tri.m == 0:
        return
    a, b = rng.normal(size=(2, tri.m)) * 2.5
    s = np.linspace(0, 1, 4001)[:, None]
    X = a + s * (b - a)
    ids, w = weights_numpy(tri, X)
    W = np.zeros((len(X), int(tri.point_ids.max()) + 1))
    np.add.at(W, (np.arange(len(X))[:, None], ids), w)
    step = np.abs(np.diff(W, axis=0)).max()
    # Lipschitz bound: the hat functions' gradients are the rows of T (and -their sum); the projection
    # onto the hull is 1-Lipschitz, so |dw| <= max|grad b| * |dx| (+ the inside tolerance's clamping)
    T = tri.transform[:, : tri.m, :]
    grads = np.concatenate([T, -T.sum(axis=1, keepdims=True)], axis=1)
    lip = np.linalg.norm(grads, axis=2).max()
    dx = np.linalg.norm(b - a) / 4000
    assert step <= 1.01 * lip * dx + 1e-6


def test_continuity_check_can_fail():
    """The bound above is tight enough to see a discontinuity: nearest *vertex* weights violate it."""
    rng = np.random.default_rng(0)
    tri = triangulate(rng.normal(size=(10, 2)))
    X = np.linspace(-2, 2, 4001)[:, None] * np.array([[1.0, 0.3]])
    near = np.argmin(((X[:, None] - tri.points[None]) ** 2).sum(-1), axis=1)
    W = np.eye(len(tri.points))[near]
    T = tri.transform[:, :2, :]
    lip = np.linalg.norm(np.concatenate([T, -T.sum(1, keepdims=True)], 1), axis=2).max()
    assert np.abs(np.diff(W, axis=0)).max() > 1.01 * lip * np.linalg.norm(X[1] - X[0]) + 1e-6
