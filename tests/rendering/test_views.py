import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from mifacerf.rendering.views import ViewSampler, to_chart
from mifacerf.rig import CAMERA_LAYOUTS, camera_ring


def dirs_from_chart(yaw, pitch):
    yaw, pitch = np.asarray(yaw, float), np.asarray(pitch, float)
    return np.stack([np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)], -1)


@pytest.fixture(scope="module")
def six():
    cams = camera_ring(CAMERA_LAYOUTS[6], width=32, height=32, target=(0, 0, 0), distortion_scale=0)
    return cams, ViewSampler.from_cameras(cams)


def test_camera_views_reproduce_the_camera(six):
    cams, vs = six
    for i, c in enumerate(cams):
        w = vs.dense((-c.forward)[None])[0]
        assert w[i] == pytest.approx(1.0, abs=1e-9)


def test_weights_are_barycentric_inside(six):
    cams, vs = six
    chart = to_chart(np.stack([-c.forward for c in cams]))
    # the centroid of cameras 0, 1, 4 (a Delaunay triangle or two) reconstructs its own chart position
    p = np.array([[0.0, 0.0], [np.radians(-20), np.radians(3)]])
    w = vs.dense(dirs_from_chart(p[:, 0], p[:, 1]))
    np.testing.assert_allclose(w @ chart, p, atol=1e-9)
    assert np.all(w >= 0) and np.allclose(w.sum(1), 1)
    assert not vs.outside(dirs_from_chart(p[:, 0], p[:, 1])).any()


SHARED = ViewSampler.from_cameras(camera_ring(CAMERA_LAYOUTS[6], width=32, height=32, target=(0, 0, 0),
                                               distortion_scale=0))


@settings(max_examples=200, deadline=None)
@given(st.floats(-1.4, 1.4), st.floats(-1.2, 1.2))
def test_weights_valid_everywhere_and_continuous(yaw, pitch):
    vs = SHARED
    eps = 1e-6
    d = dirs_from_chart([yaw, yaw + eps], [pitch, pitch + eps])
    w = vs.dense(d)
    assert np.isfinite(w).all() and (w >= 0).all()
    np.testing.assert_allclose(w.sum(1), 1.0)
    assert np.abs(w[0] - w[1]).max() < 1e-3  # no jump: the fall-back outside the hull is continuous


def test_outside_uses_nearest_hull_edge(six):
    cams, vs = six
    chart = to_chart(np.stack([-c.forward for c in cams]))
    # far to the right at the height of the top row: only the top-right camera(s) matter
    w = vs.dense(dirs_from_chart([np.radians(80)], [np.radians(10)]))[0]
    assert vs.outside(dirs_from_chart([np.radians(80)], [np.radians(10)]))[0]
    top_right = np.argmax(chart[:, 0] + chart[:, 1])
    assert w[top_right] == pytest.approx(1.0)


def test_degenerate_layouts():
    one = ViewSampler(np.array([[0, 0, 1.0]]))
    np.testing.assert_allclose(one.dense(dirs_from_chart([0.3], [0.1])), [[1.0]])
    line = ViewSampler(dirs_from_chart(np.radians([-30, 0, 30]), [0, 0, 0]))
    assert line.kind == "line"
    w = line.dense(dirs_from_chart([np.radians(15), np.radians(60)], [0.2, 0.0]))
    np.testing.assert_allclose(w[0], [0, 0.5, 0.5], atol=1e-9)
    np.testing.assert_allclose(w[1], [0, 0, 1.0], atol=1e-9)
    with pytest.raises(ValueError):
        ViewSampler(np.zeros((0, 3)))


def test_drjit_weights_agree_with_numpy(six, mi, rng):
    from mifacerf.jitarrays import to_jit

    cams, vs = six
    yaw = rng.uniform(-1.4, 1.4, 400)
    pitch = rng.uniform(-1.0, 1.0, 400)
    d = dirs_from_chart(yaw, pitch)
    ref = vs.dense(d)
    ids, w = vs.weights_jit(to_jit(mi.Vector3f, d.T))
    got = np.zeros_like(ref)
    for k in range(3):
        np.add.at(got, (np.arange(400), np.asarray(ids[k]).astype(int)), np.asarray(w[k]))
    np.testing.assert_allclose(got, ref, atol=1e-4)
