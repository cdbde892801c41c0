"""Triangulation through the rig's distorted cameras against analytic points."""
import numpy as np
import pytest

from mifacerf.geometry.triangulate import project_all, triangulate
from mifacerf.rig import CAMERA_LAYOUTS, camera_ring


@pytest.fixture(scope="module")
def cams():
    # strongly distorted lenses so an undistortion or projection mistake shows
    return camera_ring(CAMERA_LAYOUTS[6], width=256, height=256, distortion_scale=3.0, seed=4)


def test_exact_points_recovered(cams, rng):
    X = rng.normal(0, 0.05, (300, 3)) + [0, 0, 0.05]
    uv = project_all(cams, X)
    uv[rng.random(uv.shape[:2]) < 0.3] = np.nan
    tr = triangulate(cams, uv)
    ok = tr.ok
    assert ok.mean() > 0.8
    np.testing.assert_allclose(tr.points[ok], X[ok], atol=1e-9)
    assert np.nanmax(tr.error) < 1e-6
    assert (tr.n_views[ok] == np.isfinite(uv[..., 0]).sum(0)[ok]).all()


def test_fewer_than_two_views_is_flagged_not_guessed(cams):
    X = np.array([[0.0, 0.0, 0.08], [0.01, 0.02, 0.07]])
    uv = project_all(cams, X)
    uv[1:, 0] = np.nan      # point 0 seen by one camera only
    tr = triangulate(cams, uv)
    assert not tr.ok[0] and np.isnan(tr.points[0]).all() and tr.n_views[0] == 1
    assert tr.ok[1]


def test_outlier_view_is_dropped(cams, rng):
    X = rng.normal(0, 0.03, (50, 3)) + [0, 0, 0.06]
    uv = project_all(cams, X) + rng.normal(0, 0.3, (len(cams), 50, 2))
    uv[2, :, 0] += 15.0     # one camera clicked 15 px off
    robust = triangulate(cams, uv, max_error=2.0)
    naive = triangulate(cams, uv)
    e_r = np.linalg.norm(robust.points - X, axis=1)
    e_n = np.linalg.norm(naive.points - X, axis=1)
    assert np.median(e_r) < 0.5e-3 < np.median(e_n)
    assert not robust.used[2].any()


def test_noise_propagates_as_expected(cams, rng):
    """0.5 px of click noise in six views gives a 3-D error well under a pixel footprint."""
    X = rng.normal(0, 0.04, (400, 3)) + [0, 0, 0.06]
    uv = project_all(cams, X) + rng.normal(0, 0.5, (len(cams), 400, 2))
    tr = triangulate(cams, uv)
    fp = cams[0].pixel_footprint(1.3)
    err = np.linalg.norm(tr.points - X, axis=1) / fp
    assert 0.1 < np.median(err) < 0.6
    assert np.median(tr.error) == pytest.approx(0.5, rel=0.4)
