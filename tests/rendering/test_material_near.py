"""The near-field shadow rule (facerf_direct, facerf_bsdf near_occluders, self_visibility near)."""
import numpy as np
import pytest


def _two_sheets(gap: float):
    """Two parallel unit squares at z = 0 and z = gap, both facing +z (vertices, triangles)."""
    sq = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    V = np.concatenate([sq, sq + [0, 0, gap]])
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    return V, F


def test_near_rule_passes_the_mesh_within_the_distance_only(mi):
    """From the lower sheet straight up, the upper sheet 1 cm away blocks under Mitsuba's rule and under a
    near distance of 5 mm, and lets the ray through under 2 cm; sideways rays that leave the sheets are free."""
    from mifacerf.rendering.self_visibility import _free_from

    V, F = _two_sheets(0.01)
    O = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.0]])
    N = np.array([[0.0, 0.0, 1.0]] * 2)
    D = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    for near, up in ((0.0, False), (0.005, False), (0.02, True)):
        free = _free_from(V, F, O, N, D, near=near)
        assert (free[:, 0] == up).all(), (near, free)
        assert free[:, 1].all()


def test_near_occluders_is_a_checked_material_parameter(toy_model, mi):
    """facerf_bsdf near_occluders reaches the material; a negative distance names the parameter."""
    from mifacerf.variant import ensure_plugins

    ensure_plugins()

    def scene(near):
        return mi.load_dict({"type": "scene", "face": {"type": "facerf_face", "model": str(toy_model.root),
                                                       "bsdf": {"type": "facerf_bsdf", "near_occluders": near}}})

    assert scene(0.01).shapes()[0].bsdf().state.near_occluders == pytest.approx(0.01)
    with pytest.raises(Exception, match="parameter 'near_occluders'"):
        scene(-1.0)


def test_facerf_direct_is_direct_without_the_rule_and_lets_near_skin_through(toy_model, mi):
    """On the toy under the sky: facerf_direct with near_occluders 0 agrees with Mitsuba's direct (the same
    estimate but for BSDF samples, within 3 %); with a near distance larger than the head (its shadow rays pass
    all of the skin) it renders a finite, lit face."""
    from mifacerf.camera import Camera
    from mifacerf.environment import cache_dir, generated
    from mifacerf.rendering.sensors import sensor_dict
    from mifacerf.variant import ensure_plugins

    ensure_plugins()
    generated("sky")
    env = str(cache_dir() / "environments" / "sky-128.exr")
    cam = Camera.look_at("t", [0.12, 0.1, 1.0], [0, 0, 0], width=24, height=24, focal=96.0)

    def render(integrator, **bsdf):
        scene = mi.load_dict({"type": "scene", "integrator": {"type": integrator},
                              "sensor": sensor_dict(cam, spp=64), "light": {"type": "envmap", "filename": env},
                              "face": {"type": "facerf_face", "model": str(toy_model.root),
                                       "bsdf": {"type": "facerf_bsdf", **bsdf}}})
        return np.asarray(mi.render(scene, seed=0))

    direct, plain = render("direct"), render("facerf_direct")
    face = direct[..., 3] > 0.999
    assert face.any() and np.isfinite(plain).all()
    ratio = plain[..., :3][face].mean() / direct[..., :3][face].mean()
    assert abs(ratio - 1) < 0.03, ratio
    near = render("facerf_direct", near_occluders=1.0)
    assert np.isfinite(near).all() and near[..., :3][face].mean() > 0
