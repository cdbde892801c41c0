"""Harmonic dot removal: exact on harmonic images, one operator for every light, background kept out."""
import numpy as np

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
