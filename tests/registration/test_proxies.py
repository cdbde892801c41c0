"""Lighting-independent proxies: the cone opposite the camera, the percentile, the cache."""
import numpy as np
import pytest

from mifacerf.camera import Camera
from mifacerf.registration.proxies import compute_proxies, cone_weights, percentile_image
from mifacerf.rig import LightStage


def test_cone_opposite_the_camera_is_left_out():
    ls = LightStage.semicircular_arm(12, 12)
    cam = Camera.look_at("c", [0.3, 0.1, 1.3], [0, 0, 0], width=32, height=32, focal=100.0)
    w = cone_weights(ls, cam, 60.0)
    away = -cam.centre / np.linalg.norm(cam.centre)
    ang = np.degrees(np.arccos(ls.directions @ away))
    assert np.all(w[ang < 60] == 0) and np.all(w[ang > 60] == ls.solid_angles[ang > 60])
    assert 0.1 < (w == 0).mean() < 0.4


def test_diffuse_and_percentile(rng):
    ls = LightStage.semicircular_arm(6, 6)
    cam = Camera.look_at("c", [0, 0, 1.3], [0, 0, 0], width=8, height=8, focal=20.0)
    field = rng.random((len(ls), 8, 8, 3)).astype(np.float32)
    p = compute_proxies(field, ls, cam, 60.0)
    w = cone_weights(ls, cam, 60.0)
    np.testing.assert_allclose(p.diffuse, np.einsum("l,lhwc->hwc", w, field), rtol=1e-5)
    np.testing.assert_allclose(p.p95, np.percentile(field, 95, axis=0, method="closest_observation"),
                               atol=np.ptp(field) / len(ls))
    # a specular highlight in a few lights does not reach the 95th percentile
    spiky = np.full((40, 2, 2, 3), 0.2, np.float32)
    spiky[:1] = 50.0
    assert percentile_image(spiky).max() == pytest.approx(0.2)
