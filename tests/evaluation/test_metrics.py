"""The error metrics against analytic cases."""
import numpy as np
import pytest

from mifacerf.evaluation.metrics import psnr, psnr_two_truths


def test_psnr_of_a_known_error():
    ref = np.zeros((8, 8, 3))
    ref[0, 0] = 2.0                                   # peak 2
    img = ref + 0.02                                  # RMSE 0.02
    assert psnr(img, ref) == pytest.approx(20 * np.log10(2.0 / 0.02))


def test_noise_corrected_psnr_recovers_the_error_against_the_expectation(rng):
    """A truth rendered as two noisy halves: the plain PSNR is dragged down by the truth's own noise;
    subtracting the noise estimated from the halves recovers the PSNR against the noise-free truth."""
    expect = rng.uniform(0.2, 1.0, (256, 256, 3))
    image = expect + rng.normal(0, 0.01, expect.shape)             # the model's own error: 40 dB-ish
    sigma = 0.014                                                    # each half's noise
    a = expect + rng.normal(0, sigma, expect.shape)
    b = expect + rng.normal(0, sigma, expect.shape)
    r = psnr_two_truths(image, a, b)
    peak = (0.5 * (a + b)).max()
    true_db = 10 * np.log10(peak ** 2 / ((image - expect) ** 2).mean())
    floor_db = 10 * np.log10(peak ** 2 / (sigma ** 2 / 2))
    assert r["psnr"] < true_db - 1.0                                 # the noisy truth costs over 1 dB here
    assert r["psnr_noise_corrected"] == pytest.approx(true_db, abs=0.05)
    assert r["noise_floor"] == pytest.approx(floor_db, abs=0.05)
    assert r["psnr"] == pytest.approx(psnr(image, 0.5 * (a + b)))


def test_noise_corrected_psnr_of_a_perfect_image_is_infinite_or_high(rng):
    expect = rng.uniform(0.2, 1.0, (64, 64, 3))
    a = expect + rng.normal(0, 0.01, expect.shape)
    b = expect + rng.normal(0, 0.01, expect.shape)
    r = psnr_two_truths(expect, a, b)
    assert r["psnr_noise_corrected"] > r["noise_floor"] + 10 or np.isinf(r["psnr_noise_corrected"])
