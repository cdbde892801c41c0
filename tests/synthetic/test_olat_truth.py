"""The batched OLAT renderer and the path-traced truth against Mitsuba and analytic answers."""
import numpy as np
import pytest

from mifacerf import environment as E
from mifacerf.camera import Camera
from mifacerf.rig import LightStage, camera_ring
from mifacerf.synthetic.olat import render_olat
from mifacerf.synthetic.truth import render_truth

SHAPES = {
    "s": {"type": "sphere", "radius": 0.09,
          "bsdf": {"type": "principled", "base_color": {"type": "rgb", "value": [0.6, 0.4, 0.3]},
                   "roughness": 0.6}},
    "b": {"type": "sphere", "radius": 0.03, "center": [0.08, 0.06, 0.08], "bsdf": {"type": "diffuse"}},
}


@pytest.fixture(scope="module")
def cam():
    return camera_ring([(15.0, 5.0)], width=48, height=48, target=(0, 0, 0), face_height=0.26)[0]


def psnr(a, b, mask):
    return 10 * np.log10(b[mask].max() ** 2 / ((a - b)[mask] ** 2).mean())


def test_olat_equals_mitsuba_directional_emitter(mi, cam):
    d = np.array([0.3, 0.5, 0.8])
    d /= np.linalg.norm(d)
    olat = render_olat(mi.load_dict({"type": "scene", **SHAPES}), cam, d[None], irradiance=[[1.0, 2.0, 0.5]],
                       spp=4)
    scene = mi.load_dict({"type": "scene", **SHAPES, "sun": {"type": "directional", "direction": (-d).tolist(),
                                                            "irradiance": {"type": "rgb",
                                                                           "value": [1.0, 2.0, 0.5]}}})
    ref = render_truth(scene, cam, spp=4)
    assert olat[0].max() > 0.01
    np.testing.assert_allclose(olat[0], ref[..., :3], atol=1e-5)
    # the small sphere casts a shadow onto the big one: some lit-side pixels are dark
    assert (olat[0].sum(-1)[ref[..., 3] > 0.99] == 0).any()


def test_relit_olat_matches_path_traced_environment(mi, cam):
    ls = LightStage.semicircular_arm(12, 12)
    olat = render_olat(mi.load_dict({"type": "scene", **SHAPES}), cam, ls.directions, spp=4)
    env = E.generated("sky", 32)
    relit = E.relight(olat, E.light_basis(env, ls.directions, n_theta=256))
    truth = render_truth(mi.load_dict({"type": "scene", **SHAPES, "env": env.mitsuba_dict()}), cam, spp=512)
    mask = truth[..., 3] > 0.999
    # measured ~35 dB here (truth noise at 512 spp included); a wrong convention gives < 20 dB
    assert psnr(relit, truth[..., :3], mask) > 30.0
    # the environment mirrored left-right (a wrong u convention) must match far worse
    mirrored = E.Environment(env.data[:, ::-1].copy(), "mirrored")
    wrong = E.relight(olat, E.light_basis(mirrored, ls.directions, n_theta=256))
    assert psnr(wrong, truth[..., :3], mask) < psnr(relit, truth[..., :3], mask) - 6.0


def test_truth_alpha_is_projected_area(mi):
    cam = Camera.look_at("c", [0, 0, 1.0], [0, 0, 0], width=40, height=40, focal=200.0)
    truth = render_truth(mi.load_dict({"type": "scene", "s": {"type": "sphere", "radius": 0.05}}), cam, spp=16)
    # silhouette of a sphere of radius r at distance D: a disc of angular radius asin(r/D)
    r_px = 200.0 * np.tan(np.arcsin(0.05 / 1.0))
    assert truth[..., 3].sum() == pytest.approx(np.pi * r_px ** 2, rel=0.02)
    assert truth[0, 0, 3] == 0 and truth[20, 20, 3] == 1


def test_empty_scene_and_lights(mi, cam):
    out = render_olat(mi.load_dict({"type": "scene"}), cam, np.array([[0, 1.0, 0]]), spp=1)
    assert out.shape == (1, 48, 48, 3) and not out.any()
