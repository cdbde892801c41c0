"""Fiducials one view alone sees: image position from that view, depth from the estimate."""
import numpy as np
import pytest

from mifacerf.registration.consensus import free_peaks, view_peaks
from mifacerf.registration.single_view import single_view_snap

from .dotmaps import dot_grid, strength_maps


@pytest.fixture(scope="module")
def rig():
    cams, X = dot_grid()
    return cams, X, cams[0].pixel_footprint(1.3)


def only_in(cams, n, view):
    vis = np.zeros((len(cams), n), bool)
    vis[view] = True
    return vis


def test_the_point_lands_on_its_dot_ray_at_the_estimate_depth(rig):
    """Start 1 px off across the ray and 6 mm off along it: the result is on the dot's ray (the data), at the
    depth of the start (no other information), i.e. exactly the true point plus the start's depth error."""
    cams, X, fp = rig
    c, k = 2, 27
    seen = only_in(cams, len(X), c)
    peaks = [view_peaks(m, 0.1, 1.3) for m in strength_maps(cams, X, seen)]
    free = [np.ones(len(p.uv), bool) for p in peaks]
    origin = cams[c].centre
    ray = (X[k] - origin) / np.linalg.norm(X[k] - origin)
    across = np.cross(ray, [0.0, 1.0, 0.0])
    across /= np.linalg.norm(across)
    X0 = X[k] + 0.006 * ray + 1.0 * fp * across
    r = single_view_snap(cams, peaks, free, X0[None], seen[:, [k]], search_px=3.0, min_value=0.5)
    assert r.points.tolist() == [0] and r.view.tolist() == [c]
    np.testing.assert_allclose(r.X[0], X[k] + 0.006 * ray, atol=0.05 * fp)
    assert 0.5 < r.shift_px[0] < 1.5


def test_only_single_view_points_with_a_free_strong_peak_near_them(rig):
    cams, X, fp = rig
    ids = np.array([10, 20, 30, 40])
    seen = only_in(cams, len(X), 1)
    seen[3, 40] = True                               # point 40: two views, not this pass's business
    maps = strength_maps(cams, X, seen, weights=np.where(np.arange(len(X)) == 30, 0.3, 1.0))  # 30: faint
    peaks = [view_peaks(m, 0.1, 1.3) for m in maps]
    others = np.setdiff1d(np.arange(len(X)), [10, 30, 40])   # 20's dot is taken by a registered point
    free = free_peaks(peaks, cams, X[others], np.ones((len(cams), len(others)), bool), 1.0)
    r = single_view_snap(cams, peaks, free, X[ids], seen[:, ids], search_px=3.0, min_value=0.5)
    assert r.points.tolist() == [0]                  # only point 10
    # and a start beyond the search radius finds nothing
    far = X[10] + np.array([6 * fp, 0, 0])
    assert single_view_snap(cams, peaks, free, far[None], seen[:, [10]], 3.0, 0.5).points.size == 0


def test_a_peak_goes_to_the_nearer_of_two_claimants(rig):
    cams, X, fp = rig
    k = 33
    seen = only_in(cams, len(X), 0)
    peaks = [view_peaks(m, 0.1, 1.3) for m in strength_maps(cams, X[[k]], seen[:, [k]])]
    free = [np.ones(len(p.uv), bool) for p in peaks]
    starts = np.stack([X[k] + [0.5 * fp, 0, 0], X[k] + [1.8 * fp, 0, 0]])
    r = single_view_snap(cams, peaks, free, starts, np.repeat(seen[:, [k]], 2, axis=1), 3.0, 0.5)
    assert r.points.tolist() == [0]


def test_a_point_two_views_see_but_only_one_shows_is_placed(rig):
    """The mesh says views 1 and 2 see the point, but the dot shows in view 2 only (hidden in view 1 by
    something the mesh does not model): placed from view 2. Showing in both: left alone."""
    cams, X, fp = rig
    k = 22
    vis = np.zeros((len(cams), 1), bool)
    vis[[1, 2], 0] = True
    shows = np.zeros((len(cams), len(X)), bool)
    shows[2, k] = True
    peaks = [view_peaks(m, 0.1, 1.3) for m in strength_maps(cams, X, shows)]
    free = [np.ones(len(p.uv), bool) for p in peaks]
    r = single_view_snap(cams, peaks, free, X[[k]] + [0.5 * fp, 0, 0], vis, 3.0, 0.5)
    assert r.points.tolist() == [0] and r.view.tolist() == [2]
    shows[1, k] = True
    peaks = [view_peaks(m, 0.1, 1.3) for m in strength_maps(cams, X, shows)]
    free = [np.ones(len(p.uv), bool) for p in peaks]
    assert single_view_snap(cams, peaks, free, X[[k]], vis, 3.0, 0.5).points.size == 0
