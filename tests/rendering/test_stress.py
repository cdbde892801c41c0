"""Numerical stress tests (the benchmark issue's item 5): finite, bounded, documented results."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mifacerf import environment as E
from mifacerf.rendering.compression import compress_field, reconstruct
from mifacerf.rendering.lighting import RotatedLightBasis
from mifacerf.formats.model import ModelError, ModelWriter
from mifacerf.rig import LightStage




def sun_and_sky(ratio: float, h: int = 32) -> E.Environment:
    """A dim sky with a one-texel sun ``ratio`` times brighter."""
    data = np.full((h, 2 * h, 3), 0.2, np.float32)
    data[h // 4, 3 * h // 4] = 0.2 * ratio
    return E.Environment(data, f"sun{ratio:g}")


def test_extreme_hdr_environment_is_finite_and_linear(toy_model):
    from mifacerf.rendering.renderer import Renderer

    m = toy_model
    W = np.zeros((m.n_vertices, 2))
    W[:, 0] = 1
    r = Renderer(m)
    lo = r.render(m.vertices[0], W, m.cameras[1], sun_and_sky(1.0), spp=1)
    hi = r.render(m.vertices[0], W, m.cameras[1], sun_and_sky(1e5), spp=1)
    assert np.isfinite(hi).all() and hi[..., :3].max() > 100 * lo[..., :3].max()
    # relighting is linear in the environment: sun-only = (sun + sky) − sky, to float32 precision
    sky = E.Environment(np.full((32, 64, 3), 0.2, np.float32), "sky-only")
    sun = E.Environment(sun_and_sky(1e5).data - sky.data, "sun-only")
    a = r.render(m.vertices[0], W, m.cameras[1], sun, spp=1)
    b = r.render(m.vertices[0], W, m.cameras[1], sky, spp=1)
    np.testing.assert_allclose(a[..., :3] + b[..., :3], hi[..., :3], rtol=2e-3, atol=1e-3 * hi[..., :3].max())


def test_near_black_and_constant_data_compress_finitely():
    tiny = np.full((50, 8, 3), 1e-9, np.float32)
    comp = compress_field(tiny, 4)
    assert all(np.isfinite(v).all() for v in comp.values())
    np.testing.assert_allclose(reconstruct(comp), tiny, atol=1e-9)


def test_float16_storage_limits(tmp_path):
    from mifacerf.camera import Camera

    cam = Camera("c", 4, 4, np.eye(3))
    w = ModelWriter(tmp_path / "m", np.array([[0, 1.0, 0]]), [4 * np.pi], [cam], [("neutral", "neutral")],
                    np.array([[0, 1, 2]]))
    with pytest.raises(ModelError, match="overflow float16"):
        w.write_field("neutral", cam, np.zeros((1, 2)), [0], [[1, 0, 0]], [1.0], np.full((1, 1, 3), 7e4))
    with pytest.raises(ModelError, match="non-finite"):
        w.write_field("neutral", cam, np.zeros((1, 2)), [0], [[1, 0, 0]], [1.0], np.full((1, 1, 3), np.nan))
    # values far below float16's normal range keep their order of magnitude (subnormals), documented
    small = np.float16(np.float32(3e-6))
    assert abs(float(small) - 3e-6) / 3e-6 < 0.1


def test_targets_far_outside_the_captured_deformations(toy_model):
    from mifacerf.rendering.renderer import Renderer

    m = toy_model
    far = m.vertices[0] * np.array([1.6, 0.6, 1.3]) + np.array([0.01, -0.02, 0.0])
    W = m.blend.dense_weights(far[None])[0]
    assert np.isfinite(W).all() and np.allclose(W.sum(1), 1) and (W >= 0).all()
    img = Renderer(m).render(far, W, m.cameras[0], E.generated("gradient", 32), spp=1)
    assert np.isfinite(img).all() and img[..., 3].sum() > 10


def test_degenerate_light_layouts():
    three = LightStage.semicircular_arm(1, 3)
    env = E.generated("gradient", 32)
    rb = RotatedLightBasis(env, three.directions, n_theta=16)
    out = rb.rotated(Rotation.from_rotvec([[0, 0.3, 0], [0.2, 0, 0.1]]).as_matrix())
    assert np.isfinite(out).all() and (out >= 0).all()
    np.testing.assert_allclose(out.sum(1), np.broadcast_to(rb.identity.sum(0), (2, 3)), rtol=0.05)


def test_long_animation_has_no_drift(toy_model):
    """1000 frames of small random local rotations leave no state behind: frame 0 renders identically."""
    from mifacerf.rendering.renderer import Renderer

    m = toy_model
    env = E.generated("interior", 32)
    r = Renderer(m)
    W = np.zeros((m.n_vertices, 2))
    W[:, 1] = 1
    first = r.render(m.vertices[1], W, m.cameras[2], env, spp=1)
    basis = r.light_basis(env)
    rng = np.random.default_rng(3)
    state = basis.rotated(np.eye(3)[None])
    for _ in range(1000):
        state = basis.rotated(Rotation.from_rotvec(rng.normal(0, 0.05, (4, 3))).as_matrix())
    assert np.isfinite(state).all()
    again = r.render(m.vertices[1], W, m.cameras[2], env, spp=1)
    np.testing.assert_array_equal(first, again)


def test_skipped_lights_and_cached_frames(toy_model):
    """Skip what a scene does not need: negligible lights leave the image within tolerance; an unchanged
    frame comes from the cache, a changed one does not."""
    from mifacerf.camera import ring_camera
    from mifacerf.rendering.renderer import Renderer, RenderStats

    m = toy_model
    data = np.full((32, 64, 3), 0.3, np.float32)
    data[16:] = 1e-7  # the lower hemisphere is (almost) black
    env = E.Environment(data, "upper")
    W = np.zeros((m.n_vertices, 2))
    W[:, 0] = 1
    full = Renderer(m, light_epsilon=0).render(m.vertices[0], W, m.cameras[1], env, spp=1)
    r = Renderer(m, light_epsilon=1e-4)
    st = RenderStats()
    fast = r.render(m.vertices[0], W, m.cameras[1], env, spp=1, stats=st)
    assert st.lights_skipped > 5
    assert np.abs(fast - full).max() <= 1e-4 * max(full.max(), 1e-6) * 10  # stated tolerance: 1e-3 of the peak
    st2 = RenderStats()
    again = r.render(m.vertices[0], W, m.cameras[1], env, spp=1, stats=st2)
    assert st2.cached and np.array_equal(again, fast)
    st3 = RenderStats()
    r.render(m.vertices[0], W, ring_camera(m.cameras, 5.0, 0.0), env, spp=1, stats=st3)
    assert not st3.cached
