"""The image-space consensus snap: far starts, taken dots, phantoms, faint dots."""
import numpy as np
import pytest

from mifacerf.registration.consensus import consensus_snap, free_peaks, hypotheses, view_peaks
from mifacerf.geometry.triangulate import project_all

from .dotmaps import dot_grid, strength_maps


@pytest.fixture(scope="module")
def rig():
    cams, X = dot_grid()
    return cams, X, cams[0].pixel_footprint(1.3)


def setup(cams, X, target, seen, weights=None):
    maps = strength_maps(cams, X, seen, weights=weights)
    peaks = [view_peaks(m, 0.1, 1.3) for m in maps]
    others = np.setdiff1d(np.arange(len(X)), target)
    vis_all = np.ones((len(cams), len(X)), bool)
    free = free_peaks(peaks, cams, X[others], vis_all[:, others], 1.0)
    return peaks, free, others


def test_view_peaks_are_sub_pixel(rig):
    cams, X, fp = rig
    maps = strength_maps(cams, X)
    pk = view_peaks(maps[0], 0.1, 1.3)
    uv = project_all(cams, X)[0]
    uv = uv[(uv >= 2).all(1) & (uv <= 125).all(1)]
    d = np.min(np.linalg.norm(uv[:, None] - pk.uv[None], axis=-1), axis=1)
    assert len(pk.uv) >= len(uv)
    assert np.median(d) < 0.05 and np.max(d) < 0.3      # the oblique edge of the grid: blobs overlap


def test_a_dot_seen_by_two_views_far_in_depth_is_found(rig):
    """The start is 8 mm off along the depth of the two views (far outside a 3-D snap's ball) but within a
    pixel or two in both images: the two free peaks meet, and nothing else is consistent."""
    cams, X, fp = rig
    t = 24
    seen = np.ones((len(cams), len(X)), bool)
    seen[:, t] = False
    seen[[1, 4], t] = True                     # one yaw, pitch ±10°: a short baseline
    peaks, free, others = setup(cams, X, [t], seen)
    ray = X[t] - 0.5 * (cams[1].centre + cams[4].centre)
    start = X[t] + 0.008 * ray / np.linalg.norm(ray)
    vis = seen[:, [t]]
    r = consensus_snap(cams, peaks, free, start[None], vis, X[others], max_shift=8 * fp, weak_shift=1.5 * fp)
    assert r.accepted.tolist() == [0] and r.n_views[0] == 2
    assert np.linalg.norm(r.X[0] - X[t]) / fp < 0.1


def test_taken_dots_and_missing_dots_are_not_used(rig):
    """A dot that is not in the images is not registered onto a neighbour's dot, however near: those
    peaks are taken by the registered neighbours."""
    cams, X, fp = rig
    t = 24
    seen = np.ones((len(cams), len(X)), bool)
    seen[:, t] = False                         # never painted
    peaks, free, others = setup(cams, X, [t], seen)
    vis = np.ones((len(cams), 1), bool)
    # the start half-way to a neighbour
    start = 0.5 * (X[t] + X[t + 1])
    r = consensus_snap(cams, peaks, free, start[None], vis, X[others], max_shift=8 * fp, weak_shift=1.5 * fp)
    assert r.accepted.size == 0
    # without the taken test the neighbour's dot would be a perfect six-view hypothesis
    everything = [np.ones(len(p.uv), bool) for p in peaks]
    H = hypotheses(cams, peaks, everything, start[None], vis, search_px=5.0)
    assert any(h.views.sum() == 6 for h in H[0])


def test_two_points_one_dot_goes_to_nobody_or_the_nearer(rig):
    """Two unregistered points whose only candidate is one dot: the point whose start is much nearer gets
    it; with equal starts, neither."""
    cams, X, fp = rig
    a, b = 24, 25
    seen = np.ones((len(cams), len(X)), bool)
    seen[:, b] = False                         # b's dot is hidden
    peaks, free, others = setup(cams, X, [a, b], seen)
    vis = np.ones((len(cams), 2), bool)
    starts = np.stack([X[a] + np.array([0.001, 0, 0]), X[a] + np.array([-0.003, 0, 0])])
    kw = dict(max_shift=8 * fp, weak_shift=1.5 * fp)
    r = consensus_snap(cams, peaks, free, starts, vis, X[others], **kw)
    assert r.accepted.tolist() == [0]
    mid = 0.5 * (X[a] + X[b])
    r = consensus_snap(cams, peaks, free, np.stack([mid, mid]), vis, X[others], **kw)
    assert r.accepted.size == 0


def test_faint_dots_only_near_the_prediction(rig):
    """A faint dot (strength 0.3 in two views) is taken where the neighbours predict it, not 4 px away."""
    cams, X, fp = rig
    t = 24
    seen = np.ones((len(cams), len(X)), bool)
    seen[:, t] = False
    seen[[0, 1], t] = True
    w = np.ones(len(X))
    w[t] = 0.3
    peaks, free, others = setup(cams, X, [t], seen, weights=w)
    vis = seen[:, [t]]
    kw = dict(max_shift=8 * fp, weak_shift=1.5 * fp)
    near = consensus_snap(cams, peaks, free, (X[t] + np.array([0.0005, 0, 0]))[None], vis, X[others], **kw)
    assert near.accepted.tolist() == [0]
    far = consensus_snap(cams, peaks, free, (X[t] + np.array([0.0045, 0.002, 0]))[None], vis, X[others], **kw)
    assert far.accepted.size == 0 and "faint dots away from the prediction" in far.rejected
    # the same dot painted clearly is found from there
    peaks2, free2, _ = setup(cams, X, [t], seen)
    clear = consensus_snap(cams, peaks2, free2, (X[t] + np.array([0.0045, 0.002, 0]))[None], vis, X[others], **kw)
    assert clear.accepted.tolist() == [0]
