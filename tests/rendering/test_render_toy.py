"""The rendering chain (build → plan → relight → sample) on the toy capture (tests/helpers/toy.py)."""
import numpy as np
import pytest
from scipy.ndimage import binary_dilation

from mifacerf import environment as E
from mifacerf.formats.capture import Capture
from mifacerf.camera import Camera
from mifacerf.rendering.build import build_model
from mifacerf.rendering.frame import outline_texels
from mifacerf.formats.model import ModelError
from mifacerf.rendering.model import Model
from mifacerf.rendering.renderer import Renderer, RenderStats
from mifacerf.synthetic.olat import render_olat

from helpers.toy import N_T, deform, make_toy, scene_for


@pytest.fixture(scope="module")
def toy(tmp_path_factory, mi):
    root = tmp_path_factory.mktemp("toy")
    cap, rig, _ = make_toy(root, names=("neutral", "stretch", "turn"), size=48, n_pos=8, n_str=6,
                           truth_registration=True)
    build_model(cap, root / "model")
    return root, Capture(cap), Model(root / "model"), rig


def psnr(a, b, mask):
    return 10 * np.log10(b[mask].max() ** 2 / ((a - b)[mask] ** 2).mean())


def one_hot(model, name):
    W = np.zeros((model.n_vertices, len(model.expressions)))
    W[:, model.expression_index(name)] = 1.0
    return W


def test_captured_expression_and_camera_reproduce_the_relit_capture(toy):
    root, cap, model, rig = toy
    env = E.generated("interior", 32)
    r = Renderer(model)
    for name in ("neutral", "turn"):
        s = model.expression_index(name)
        cam = model.cameras[1]
        img = r.render(model.vertices[s], one_hot(model, name), cam, env, spp=1)
        ref = E.relight(cap.field(name, cam.name), E.light_basis(env, model.light_directions))
        # the field's texels on the outline (their pixels mix the surface with the backdrop) are not read
        outline = outline_texels(model.field(s, 1).depth_map())
        mask = (img[..., 3] > 0.999) & ~binary_dilation(outline)
        assert mask.sum() > 0.3 * mask.size
        assert psnr(img[..., :3], ref, mask) > 60.0  # float16 storage is the only difference


def test_in_between_expression_and_novel_view(toy, mi):
    """Half-way between neutral and stretch, seen from a camera between the capture cameras."""
    root, cap, model, rig = toy
    env = E.generated("sky", 32)
    target_fine = deform("mix")
    W = np.zeros((model.n_vertices, len(model.expressions)))
    W[:, model.expression_index("neutral")] = 0.5
    W[:, model.expression_index("stretch")] = 0.5
    cam = Camera.look_at("novel", [0.35, 0.05, 1.25], [0, 0, 0], width=48, height=48,
                         focal=rig.cameras[0].K[0, 0])
    img = Renderer(model).render(target_fine[:N_T], W, cam, env, spp=4)
    scene = mi.load_dict({"type": "scene", **scene_for(target_fine, mi)})
    olat = render_olat(scene, cam, model.light_directions, spp=4)
    ref = E.relight(olat, E.light_basis(env, model.light_directions))
    mask = img[..., 3] > 0.999
    # measured 27.8 dB: view interpolation between cameras 35° apart, sub-pixel dots and the coarse template;
    # a wrong texture mapping or lighting rotation gives < 20 dB
    assert psnr(img[..., :3], ref, mask) > 26.0


def test_unused_fields_are_never_loaded(toy):
    root, cap, model, rig = toy
    m = Model(root / "model")
    r = Renderer(m)
    st = RenderStats()
    r.render(m.vertices[0], one_hot(m, "neutral"), m.cameras[0], E.generated("gradient", 32), spp=1, stats=st)
    names = {e for e, _ in m.loaded_fields}
    assert names == {"neutral"}
    assert st.fields_loaded and all(e == "neutral" for e, _ in st.fields_loaded)


def test_bad_inputs(toy):
    root, cap, model, rig = toy
    r = Renderer(model)
    env = E.generated("sky", 32)
    W = one_hot(model, "neutral")
    bad = model.vertices[0].copy()
    bad[3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        r.render(bad, W, model.cameras[0], env)
    with pytest.raises(ValueError, match="template"):
        r.render(model.vertices[0][:-1], W, model.cameras[0], env)
    (root / "model" / "fields" / "stretch" / "cam2.rf.npy").rename(root / "model" / "moved.npy")
    try:
        with pytest.raises(ModelError, match="cam2.rf.npy: missing"):
            Model(root / "model").field(model.expression_index("stretch"), 2)
    finally:
        (root / "model" / "moved.npy").rename(root / "model" / "fields" / "stretch" / "cam2.rf.npy")


def test_exact_kernels_agree_with_the_dense_numpy_reference(toy):
    """The Dr.Jit path (chunks, lit textures, occlusion-aware lookup) against a plain NumPy sum over
    every light of every field."""
    from mifacerf.evaluation.dense_reference import dense_render
    from mifacerf.evaluation.metrics import psnr as psnr_

    root, cap, model, rig = toy
    r = Renderer(model)
    env = E.generated("interior", 32)
    W = np.zeros((model.n_vertices, len(model.expressions)))
    W[:, model.expression_index("neutral")] = 0.3
    W[:, model.expression_index("turn")] = 0.7
    target = 0.3 * model.vertices[0] + 0.7 * model.vertices[model.expression_index("turn")]
    cam = Camera.look_at("novel", [0.2, 0.1, 1.25], [0, 0, 0], width=40, height=40, focal=rig.cameras[0].K[0, 0] * 40 / 48)
    fast = r.render(target, W, cam, env, spp=1)
    dense = dense_render(r, target, W, cam, env, spp=1)
    np.testing.assert_array_equal(fast[..., 3], dense[..., 3])
    assert psnr_(fast, dense, fast[..., 3] > 0) > 60.0  # float32 vs float64 rounding only


@pytest.mark.parametrize("eye, covered", [([1.3, 0.0, -0.2], True),     # 99° from the front: beside the head
                                          ([0.0, 0.1, -1.3], True),     # from behind
                                          ([0.0, 0.0, 1.3], False)])    # looking away from the face
def test_camera_far_outside_the_captured_views(toy, eye, covered):
    """Outside the cameras' hull the view falls back to the hull's nearest edge (documented in
    rendering/views.py): the image is finite, non-negative and counted as a fall-back; a camera that sees
    nothing of the face gives an empty, transparent image, not NaN."""
    root, cap, model, rig = toy
    target = [0, 0, 0] if covered else [0, 0, 3.0]
    cam = Camera.look_at("far", eye, target, width=32, height=32, focal=rig.cameras[0].K[0, 0] * 32 / 48)
    stats = RenderStats()
    img = Renderer(model).render(model.vertices[0], one_hot(model, "neutral"), cam, E.generated("sky", 32),
                                 spp=1, stats=stats)
    assert np.isfinite(img).all() and (img >= 0).all()
    if covered:
        assert (img[..., 3] > 0.5).sum() > 20 and img[..., :3].max() > 0
        assert stats.fallback_samples > 0
    else:
        assert img.max() == 0


def test_the_renderer_keeps_the_bases_of_its_last_few_environments(toy_model):
    """A sequence lit by a new environment each frame holds at most ``KEPT_BASES`` rotated light bases (it
    had kept one per environment object for ever); the most recent one is reused, not rebuilt."""
    r = Renderer(toy_model)
    envs = [E.Environment(np.full((16, 32, 3), 0.1 * (k + 1), np.float32), f"grey{k}") for k in range(7)]
    bases = [r.light_basis(e) for e in envs]
    assert len(r._bases) == Renderer.KEPT_BASES
    assert r.light_basis(envs[-1]) is bases[-1] and r.light_basis(envs[-4]) is bases[-4]
    assert r.light_basis(envs[0]) is not bases[0]     # dropped, built again
    assert len(r._bases) == Renderer.KEPT_BASES
