"""Lip / eyelid relaxation onto rotoscoped curves, and propagation behind the margin."""
import numpy as np

from mifacerf.registration.contours import closest_on_polyline, propagate, relax_margin, rings
from mifacerf.rig import CAMERA_LAYOUTS, camera_ring


def test_closest_point_on_polyline():
    poly = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    q, t = closest_on_polyline(poly, np.array([[5.0, 2.0], [12.0, 5.0], [-3.0, -1.0]]))
    np.testing.assert_allclose(q, [[5, 0], [10, 5], [0, 0]])
    np.testing.assert_allclose(np.abs(t), [[1, 0], [0, 1], [1, 0]])


def lip(n=15, open_=0.0):
    x = np.linspace(-0.025, 0.025, n)
    return np.stack([x, -0.067 + open_ * (1 - (x / 0.025) ** 2) - 0.01 * (x / 0.025) ** 2,
                     0.105 - 25 * x ** 2], 1)


def test_margin_relaxes_onto_two_views(rng):
    cams = camera_ring(CAMERA_LAYOUTS[6], width=256, height=256, seed=3)
    camd = {c.name: c for c in cams}
    truth = lip(open_=0.004)
    views = {}
    for name in ("cam1", "cam4", "cam0"):   # two views across the curve (pitch ±10°) and one beside
        uv, _ = camd[name].project(np.concatenate([truth[:1], (truth[:-1] + truth[1:]) / 2, truth[-1:]]))
        views[name] = uv + rng.normal(0, 0.3, uv.shape)
    start = lip(open_=0.0) + np.array([0.0, 0.0, 0.002])          # closed lips, 2 mm too deep
    fp = cams[0].pixel_footprint(1.3)
    X = relax_margin(start, views, camd)
    before = np.linalg.norm(start - truth, axis=1) / fp
    after = np.linalg.norm(X - truth, axis=1) / fp
    dense = lip(400, open_=0.004)                                   # distance to the true curve (sliding
    across = np.min(np.linalg.norm(X[:, None] - dense[None], axis=-1), axis=1) / fp   # along it is unseen)
    assert np.median(before) > 2.0          # the start is well off (2.5 px before the rig framed 0.34 m)
    assert np.median(across) < 0.5 and across.max() < 1.5
    assert np.median(after) < 0.3 * np.median(before)
    # silhouettes meet the curves
    for name, poly in views.items():
        p, _ = camd[name].project(X)
        q, _ = closest_on_polyline(poly, p)
        assert np.sqrt(np.mean(np.sum((p - q) ** 2, 1))) < 0.4


def test_relaxation_without_views_keeps_the_estimate():
    start = lip()
    np.testing.assert_array_equal(relax_margin(start, {}, {}), start)


def test_propagation_is_harmonic_behind_the_margin():
    # a strip of vertices: row 0 the margin, row 3 fixed fiducials
    nx, ny = 6, 4
    V = np.stack(np.meshgrid(np.arange(nx) * 0.01, np.arange(ny) * 0.01), -1).reshape(-1, 2)
    V = np.concatenate([V, np.zeros((len(V), 1))], 1)
    F = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            a = j * nx + i
            F += [[a, a + 1, a + nx], [a + 1, a + nx + 1, a + nx]]
    F = np.array(F)
    margin = np.arange(nx)
    after = V.copy()
    after[margin, 2] += 0.003
    d = rings(len(V), F, margin, 2)
    assert d[margin].max() == 0 and d[nx:2 * nx].max() == 1 and (d[3 * nx:] == -1).all()
    movable = np.flatnonzero((d >= 1))
    out = propagate(V, after, F, margin, movable)
    dz = out[:, 2].reshape(ny, nx)
    # linear fall-off from the margin (3 mm) to the fixed row (0)
    np.testing.assert_allclose(dz[:, 2:4].mean(1), [0.003, 0.002, 0.001, 0.0], atol=3e-4)
