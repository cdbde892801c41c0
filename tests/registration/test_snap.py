"""3-D snap and the progressive snap-to on strength maps with known dots."""
import numpy as np
import pytest

from mifacerf.registration.snap import Views, ball, dot_graph, progressive_snap, snap

from .dotmaps import dot_grid, strength_maps


@pytest.fixture(scope="module")
def rig():
    return dot_grid()


def test_ball_offsets():
    b = ball(1.0, 0.5)
    assert (b[0] == 0).all() and np.all(np.linalg.norm(b, axis=1) <= 1.0 + 1e-12)
    assert len(b) == 33


def test_snap_finds_dots_to_a_fraction_of_a_pixel(rig, rng):
    cams, X = rig
    views = Views(cams, strength_maps(cams, X), centroid_sigma=1.3)
    fp = cams[0].pixel_footprint(1.3)
    start = X + rng.normal(0, 1.0 * fp, X.shape)
    vis = np.ones((len(cams), len(X)), bool)
    r = snap(views, start, vis, radius=3 * fp, step=0.5 * fp)
    assert r.ok.all()
    err = np.linalg.norm(r.X - X, axis=1) / fp
    assert np.median(err) < 0.1 and err.max() < 0.3
    assert np.all(r.strength > 4.5)        # ~1 per view, six views


def test_snap_without_a_dot_does_not_succeed(rig):
    cams, X = rig
    views = Views(cams, strength_maps(cams, X[:10]))
    fp = cams[0].pixel_footprint(1.3)
    vis = np.ones((len(cams), 1), bool)
    r = snap(views, X[20:21], vis, radius=2 * fp, step=0.5 * fp)
    assert not r.ok[0] and r.strength[0] < 0.5


def test_progressive_snap_propagates_offsets_and_marks_failures(rig, rng):
    """A large smooth offset between prediction and truth (beyond the search radius) is recovered
    by propagating offsets from the known points; a dot that is not in the images is never snapped."""
    cams, X = rig
    fp = cams[0].pixel_footprint(1.3)
    shift = np.array([0.012, -0.007, 0.004])         # ~6 px: beyond the search, nearer other dots
    pred = X - shift + rng.normal(0, 0.3 * fp, X.shape)
    missing = 27                                     # this dot was never painted
    present = np.setdiff1d(np.arange(len(X)), [missing])
    views = Views(cams, strength_maps(cams, X[present]), centroid_sigma=1.3)
    from scipy.spatial import Delaunay
    F = Delaunay(X[:, :2]).simplices
    nb = dot_graph(len(X), F, np.ones(len(X), bool))
    known = {i: X[i] for i in (0, 55)}
    vis = np.ones((len(cams), len(X)), bool)
    r = progressive_snap(views, pred, np.arange(len(X)), nb, known, vis, radius=3 * fp, step=0.5 * fp,
                         min_separation=1.0 * fp)
    assert not r.snapped[missing]
    ok = np.setdiff1d(present, list(known))
    assert r.snapped[ok].all()
    assert np.max(np.linalg.norm(r.X[ok] - X[ok], axis=1)) < 0.3 * fp
    assert r.schedule[0] == pytest.approx(max(r.strength[0], r.strength[55]))
    # without propagation (every point snapped from its own prediction) the shift is too large
    direct = snap(views, pred[ok], vis[:, ok], radius=3 * fp, step=0.5 * fp)
    assert np.mean(np.linalg.norm(direct.X - X[ok], axis=1) < 0.3 * fp) < 0.5


def test_dot_graph_links_dots_through_non_dots():
    F = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]])
    is_dot = np.array([True, False, True, False, True])
    nb = dot_graph(5, F, is_dot)
    assert set(nb[0]) == {2, 4} or set(nb[0]) == {2}
    assert 0 in nb[2] and 4 in nb[2]
    assert all(is_dot[n].all() for n in nb)


def test_two_view_snap_refuses_a_phantom_shifted_in_depth(rig):
    """Two views with a short baseline (one yaw, pitch ±10°): the right dot in one and a different dot in the
    other, a little off its epipolar line, meet at a point a centimetre deeper. Both images move by little
    more than a pixel, so only the 3-D bound exposes it."""
    cams, X = rig
    fp = cams[0].pixel_footprint(1.3)
    t = 24
    ray = X[t] - cams[1].centre
    Xp = X[t] + 0.010 * ray / np.linalg.norm(ray)          # same pixel in cam1, deeper
    maps = [np.zeros((128, 128), np.float32) for _ in cams]
    maps[1] = strength_maps(cams, X[t:t + 1])[1]
    maps[4] = strength_maps(cams, Xp[None])[4]
    views = Views(cams, maps, centroid_sigma=1.3)
    vis = np.zeros((len(cams), 1), bool)
    vis[[1, 4], 0] = True
    free = snap(views, X[t:t + 1], vis, radius=3 * fp, step=0.5 * fp)
    assert free.ok[0] and np.linalg.norm(free.X[0] - Xp) < 0.5 * fp     # the phantom, without the bound
    bounded = snap(views, X[t:t + 1], vis, radius=3 * fp, step=0.5 * fp, two_view_max_shift=3.5 * fp)
    assert not bounded.ok[0]


def test_known_points_that_are_not_targets_still_hold_their_dots(rig):
    """``dot_holders``: a refit round snaps only the fiducials left, the registered ones fixed as known
    points; a fiducial whose own dot is missing and whose prediction lies on a registered one's dot must
    not take that dot (one image dot, one fiducial), with or without them among the targets."""
    cams, X = rig
    fp = cams[0].pixel_footprint(1.3)
    from scipy.spatial import Delaunay
    F = Delaunay(X[:, :2]).simplices
    nb = dot_graph(len(X), F, np.ones(len(X), bool))
    lost = 27                                        # its own dot was never painted
    present = np.setdiff1d(np.arange(len(X)), [lost])
    views = Views(cams, strength_maps(cams, X[present]), centroid_sigma=1.3)
    near = int(np.argsort(np.linalg.norm(X - X[lost], axis=1))[1])
    pred = X.copy()
    pred[lost] = X[near] + np.array([0.3, 0.2, 0.0]) * fp    # predicted onto its neighbour's dot
    known = {int(i): X[i] for i in present}
    vis = np.ones((len(cams), len(X)), bool)
    kw = dict(radius=3 * fp, step=0.5 * fp, min_separation=1.0 * fp)
    free = progressive_snap(views, pred, np.array([lost]), nb, known, vis, **kw)
    assert free.snapped[lost]                        # without the rule, the neighbour's dot is taken
    held = progressive_snap(views, pred, np.array([lost]), nb, known, vis, dot_holders=present, **kw)
    assert not held.snapped[lost]
