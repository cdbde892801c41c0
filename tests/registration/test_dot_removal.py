"""Harmonic dot removal: exact on harmonic images, one operator for every light, background kept out."""
import numpy as np
import pytest

from mifacerf.registration.dot_removal import Inpainter, dot_mask


def test_mask_radius_per_dot():
    m = dot_mask((40, 40), np.array([[10.2, 10.7], [30.0, 30.0], [np.nan, 3]]), np.array([1.0, 2.5, 1.0]))
    assert m[11, 10] and not m[13, 10]
    assert m[32, 30] and not m[33, 30]
    assert m.sum() == (m[:20, :20].sum() + m[20:, 20:].sum())


def test_fill_reproduces_harmonic_images_for_all_lights(rng):
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    harmonic = np.stack([0.3 * xx + 0.1 * yy, xx * yy / 100.0, xx ** 2 - yy ** 2], -1) / 50.0
    lights = np.stack([harmonic * k for k in (1.0, 0.5, 2.0)])           # (L, H, W, 3)
    m = dot_mask((h, w), rng.uniform(5, 40, (8, 2)), 2.5)
    inp = Inpainter(m)
    vals = inp.fill(lights)
    assert vals.shape == (3, len(inp), 3)
    truth = lights[:, inp.pixels[:, 0], inp.pixels[:, 1]]
    np.testing.assert_allclose(vals, truth, atol=1e-4)
    # a yellow dot painted into the image is gone after the fill
    img = harmonic.copy()
    img[m] = [1.0, 1.0, 0.0]
    out = inp.apply(img)
    np.testing.assert_allclose(out, harmonic, atol=1e-4)


def test_background_is_never_blended_in():
    h, w = 30, 30
    img = np.zeros((h, w, 3), np.float32)
    img[:, :15] = 0.5                                      # face on the left, background on the right
    valid = img[..., 0] > 0
    m = dot_mask((h, w), np.array([[13.5, 15.0]]), 3.0)  # a dot on the silhouette
    img[m & valid] = [1.0, 1.0, 0.0]
    inp = Inpainter(m, valid)
    out = inp.apply(img)
    assert np.all(out[valid] == 0.5) and np.all(out[~valid] == 0)
    assert valid[inp.pixels[:, 0], inp.pixels[:, 1]].all()


def _lit_field(albedo, shading):
    """(L, H, W, 3) images = shading (L, H, W) × albedo (H, W, 3): a Lambertian field."""
    return (shading[..., None] * albedo[None]).astype(np.float32)


def test_texture_fill_keeps_each_lights_shadow_edge_through_a_dot():
    """A light stage's field: 24 soft lights and one whose shadow edge crosses a dot. The ink changes
    the colour only, so the lights' shares at the dot are the skin's and the fill recovers the
    dotless skin under the shadowing light too; the harmonic fill blurs its edge away."""
    from mifacerf.registration.dot_removal import shading_ratio_fill

    h, w = 40, 40
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    skin = np.broadcast_to(np.array([0.6, 0.45, 0.4]), (h, w, 3)).copy()
    angles = np.linspace(0, 2 * np.pi, 24, endpoint=False)
    soft = [0.5 + 0.004 * (np.cos(a) * xx + np.sin(a) * yy) for a in angles]
    edge = np.where(xx < 20.3, 1.0, 0.1)
    shading = np.stack(soft + [edge])                                         # (25, H, W)
    truth = _lit_field(skin, shading)
    m = dot_mask((h, w), np.array([[20.0, 20.0], [8.0, 30.0]]), 3.0)
    dotted = skin.copy()
    dotted[m] = [0.9, 0.85, 0.05]                                              # yellow ink
    field = _lit_field(dotted, shading)
    inp = Inpainter(m)
    ref = truth[-1, inp.pixels[:, 0], inp.pixels[:, 1]]                        # the shadowing light
    err_t = np.abs(shading_ratio_fill(inp, field)[-1] - ref).max() / ref.max()
    err_h = np.abs(inp.fill(field)[-1] - ref).max() / ref.max()
    assert err_t < 0.05, err_t
    assert err_h > 5 * err_t, (err_h, err_t)


def test_texture_fill_continues_a_skin_texture_better_than_harmonic():
    from mifacerf.registration.dot_removal import shading_ratio_fill

    h, w = 64, 64
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    pattern = 0.5 + 0.25 * np.sin(2 * np.pi * (xx / 5.0 + yy / 9.0))             # fine, oriented texture
    skin = pattern[..., None] * np.array([0.9, 0.7, 0.6])
    shading = np.stack([0.8 + 0.002 * xx, 0.3 + 0.004 * yy])
    truth = _lit_field(skin, shading)
    centres = np.array([[16.0, 16.0], [40.0, 22.0], [28.0, 45.0], [48.0, 48.0]])
    m = dot_mask((h, w), centres, 2.5)
    dotted = skin.copy()
    dotted[m] = [0.9, 0.85, 0.05]
    inp = Inpainter(m)
    ref = truth[:, inp.pixels[:, 0], inp.pixels[:, 1]]
    field = _lit_field(dotted, shading)
    rms_t = np.sqrt(((shading_ratio_fill(inp, field) - ref) ** 2).mean())
    rms_h = np.sqrt(((inp.fill(field) - ref) ** 2).mean())
    assert rms_t < 0.6 * rms_h, (rms_t, rms_h)


def test_texture_fill_keeps_the_background_out_and_falls_back_without_signal():
    from mifacerf.registration.dot_removal import shading_ratio_fill

    h, w = 30, 30
    img = np.zeros((2, h, w, 3), np.float32)
    img[:, :, :15] = [[[0.5, 0.4, 0.3]]], [[[0.25, 0.2, 0.15]]]       # face on the left, two lights
    valid = img[0, ..., 0] > 0
    m = dot_mask((h, w), np.array([[13.5, 15.0]]), 3.0)              # a dot on the silhouette
    img[0, m & valid] = [1.0, 1.0, 0.0]                                # the ink, lit like the skin
    img[1, m & valid] = [0.5, 0.5, 0.0]
    inp = Inpainter(m, valid)
    assert valid[inp.pixels[:, 0], inp.pixels[:, 1]].all()
    vals = shading_ratio_fill(inp, img, valid)
    # the colour and each light's share are the face's; the brightness may fall off towards the dark
    # surround by a few per cent (a real silhouette's falloff), never towards the background's black
    for k, colour in enumerate(([0.5, 0.4, 0.3], [0.25, 0.2, 0.15])):
        ratio = vals[k] / np.array(colour)
        np.testing.assert_allclose(ratio, ratio[:, :1].repeat(3, 1), rtol=1e-5)
        assert (ratio > 0.9).all() and (ratio < 1.02).all(), (ratio.min(), ratio.max())  # 8-bit steps, ringing
    # no red/green signal at all (a blue-only field): the harmonic values
    blue = np.zeros_like(img)
    blue[..., 2] = img[..., 2] + 0.1
    np.testing.assert_allclose(shading_ratio_fill(inp, blue, valid), inp.fill(blue), atol=1e-6)


def test_each_dot_fill_through_its_dispatcher():
    """DOT_FILL_METHODS by name: each fill through fill_dots; the default is the texture-aware fill;
    an unknown name is refused (by the dispatcher, Options and the CLI) with the choices."""
    from mifacerf.registration import dot_removal as DR
    from mifacerf.registration.cli import register_cmd
    from mifacerf.registration.register import Options

    h = w = 32
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    field = np.stack([np.stack([0.2 + 0.01 * xx, 0.3 + 0.005 * yy, 0.1 + 0 * xx], -1) * k for k in (1.0, 0.5)])
    inp = DR.Inpainter(DR.dot_mask((h, w), np.array([[15.0, 16.0]]), 3.0))
    for method, fill in DR.DOT_FILL_METHODS.items():
        got = DR.fill_dots(inp, field, None, method=method)
        assert got.shape == (2, len(inp), 3) and np.isfinite(got).all()
        np.testing.assert_array_equal(got, fill(inp, field, None))
    np.testing.assert_array_equal(DR.fill_dots(inp, field, method="harmonic"), inp.fill(field))
    np.testing.assert_array_equal(DR.fill_dots(inp, field), DR.shading_ratio_fill(inp, field))
    with pytest.raises(ValueError, match="unknown dot fill method 'blur'; choose one of texture, harmonic"):
        DR.fill_dots(inp, field, method="blur")
    with pytest.raises(ValueError, match="unknown dot fill method 'blur'"):
        Options(dot_fill="blur")
    assert Options().dot_fill == DR.DEFAULT_DOT_FILL_METHOD == next(iter(DR.DOT_FILL_METHODS))
    option = next(p for p in register_cmd.params if p.name == "dot_fill")
    assert list(option.type.choices) == list(DR.DOT_FILL_METHODS) and option.default == "texture"
