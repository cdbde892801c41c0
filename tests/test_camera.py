import cv2
import numpy as np
import pytest

from mifacerf.camera import Camera, stratified_pixel_samples
from mifacerf.rig import preset


@pytest.fixture
def cam():
    return preset("draft").rig().cameras[0]


def test_projection_matches_opencv(cam, rng):
    pts = rng.normal(0, 0.06, (200, 3))
    uv, z = cam.project(pts)
    rvec, _ = cv2.Rodrigues(cam.R)
    ref, _ = cv2.projectPoints(pts, rvec, cam.t, cam.K, cam.dist)
    assert np.all(z > 0)
    np.testing.assert_allclose(uv, ref.reshape(-1, 2), atol=1e-9)


def test_pixel_rays_pass_through_projected_points(cam, rng):
    pts = rng.normal(0, 0.06, (200, 3))
    uv, _ = cam.project(pts)
    o, d = cam.pixel_rays(uv)
    dist = np.linalg.norm(np.cross(pts - o, d), axis=1)
    assert dist.max() < 1e-9
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)


def test_look_at_orientation():
    """A frontal camera sees +Y up (smaller v) and +X on the right (larger u)."""
    cam = Camera.look_at("c", [0, 0, 1.0], [0, 0, 0], width=100, height=80, focal=100)
    uv, _ = cam.project(np.array([[0, 0, 0], [0, 0.1, 0], [0.1, 0, 0]]))
    centre, up, right = uv
    np.testing.assert_allclose(centre, [49.5, 39.5])
    assert up[1] < centre[1] and abs(up[0] - centre[0]) < 1e-9
    assert right[0] > centre[0] and abs(right[1] - centre[1]) < 1e-9
    np.testing.assert_allclose(cam.centre, [0, 0, 1.0], atol=1e-12)


def test_stratified_samples_cover_each_pixel_once_per_stratum():
    s = stratified_pixel_samples(5, 4, 4, seed=3).reshape(4, 5, 4, 2)
    jj, ii = np.meshgrid(np.arange(5), np.arange(4))
    off = s - np.stack([jj, ii], -1)[:, :, None, :]
    assert np.all(np.abs(off) <= 0.5)
    # each of the 2x2 strata holds exactly one sample
    quad = (off[..., 0] > 0).astype(int) + 2 * (off[..., 1] > 0).astype(int)
    assert np.all(np.sort(quad, axis=-1) == np.arange(4))


def test_bad_calibration_rejected():
    with pytest.raises(ValueError, match="rotation"):
        Camera("c", 10, 10, np.eye(3), R=np.diag([1, 1, -1.0]))
    with pytest.raises(ValueError, match="non-finite"):
        Camera("c", 10, 10, np.eye(3), t=[0, np.nan, 0])


def test_dict_round_trip(cam):
    c2 = Camera.from_dict(cam.to_dict())
    for a in ("K", "dist", "R", "t"):
        np.testing.assert_array_equal(getattr(c2, a), getattr(cam, a))
