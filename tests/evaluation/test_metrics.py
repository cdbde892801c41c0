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


def _disc(n=64, r=20.0):
    jj, ii = np.meshgrid(np.arange(n), np.arange(n))
    return ((jj - n / 2 + 0.5) ** 2 + (ii - n / 2 + 0.5) ** 2) <= r * r


def test_half_covered_disc_iou_and_uncovered_share_are_exact():
    from mifacerf.evaluation.metrics import silhouette_iou, uncovered

    disc = _disc()
    half = disc.copy()
    half[:, 32:] = False                              # the model covers the disc's left half
    assert silhouette_iou(half.astype(float), disc.astype(float)) == pytest.approx(half.sum() / disc.sum())
    assert half.sum() / disc.sum() == pytest.approx(0.5)   # symmetric disc: exactly half
    share, where = uncovered(half.astype(float), disc.astype(float))
    assert share == pytest.approx(0.5)
    assert np.array_equal(where, disc & ~half)


def test_soft_iou_counts_partial_coverage():
    from mifacerf.evaluation.metrics import silhouette_iou

    t = np.ones((4, 4))
    assert silhouette_iou(np.full((4, 4), 0.25), t) == pytest.approx(0.25)
    assert silhouette_iou(t, t) == 1.0


def test_composite_psnr_identical_is_infinite_and_missing_region_closed_form():
    from mifacerf.evaluation.metrics import composite_psnr

    disc = _disc()
    plate = np.full((64, 64, 3), 0.2)
    truth = np.zeros((64, 64, 4))
    truth[disc] = (0.8, 0.8, 0.8, 1.0)                # premultiplied, full coverage
    assert composite_psnr(truth, truth, plate) == float("inf")
    img = truth.copy()
    miss = disc.copy()
    miss[:, :48] = False                              # the model misses the disc's right strip
    img[miss] = 0.0
    # over the disc (the union of coverages): the missed pixels show the plate (0.2) instead of 0.8
    mse = miss.sum() / disc.sum() * 0.6 ** 2
    assert composite_psnr(img, truth, plate) == pytest.approx(10 * np.log10(0.8 ** 2 / mse))
    extra = truth.copy()
    ring = _disc(r=24.0) & ~disc                      # extra coverage the truth does not have
    extra[ring] = (0.5, 0.5, 0.5, 1.0)
    union = disc | ring
    mse = ring.sum() / union.sum() * 0.3 ** 2
    assert composite_psnr(extra, truth, plate) == pytest.approx(10 * np.log10(0.8 ** 2 / mse))


def test_coverage_picture_labels_missed_and_extra():
    from mifacerf.evaluation.metrics import coverage_picture

    a = np.array([[1.0, 0.0], [1.0, 0.0]])
    t = np.array([[1.0, 1.0], [0.0, 0.0]])
    pic = coverage_picture(a, t)
    assert tuple(pic[0, 1]) == (1.0, 0.0, 0.0)        # truth only: missed, red
    assert pic[1, 0, 2] == 1.0 and pic[1, 0, 0] == 0  # model only: extra, blue
    assert pic[1, 1].sum() == 0


def test_error_regions_split_the_composite_error_exactly():
    """A truth disc whose inner half is the face and outer ring an extension; the render covers the face
    exactly, misses the ring's right strip and adds a patch outside: the shares are closed form."""
    from scipy.ndimage import binary_dilation

    from mifacerf.evaluation.metrics import REGIONS, error_regions, region_map

    n = 64
    disc, face = _disc(n, 24.0), _disc(n, 12.0)
    plate = np.full((n, n, 3), 0.2)
    truth = np.zeros((n, n, 4))
    truth[disc] = (0.8, 0.8, 0.8, 1.0)
    img = truth.copy()
    img[face, :3] = 0.7                               # face error 0.1 per channel
    miss = disc & ~face
    miss[:, :44] = False                              # the right part of the ring missed: plate (0.2) shows
    img[miss] = 0.0
    extra = np.zeros((n, n), bool)
    extra[2:6, 2:6] = True                            # far from the disc
    img[extra] = (0.5, 0.5, 0.5, 1.0)
    labels = region_map(img[..., 3], truth[..., 3], face)
    # silhouette: both sides of each outline (the truth's circle, the render's cut and the patch's edge)
    edge = np.zeros((n, n), bool)
    for fg in (disc, disc & ~miss | extra, extra):
        edge |= (binary_dilation(fg) & ~fg) | (binary_dilation(~fg) & fg)
    edge &= disc | extra                              # scored: where either has coverage
    assert np.array_equal(labels == 3, edge)
    assert np.array_equal(labels == 1, face & ~edge)
    assert np.array_equal(labels == 2, disc & ~face & ~edge)
    assert np.array_equal(labels == 4, extra & ~edge)
    assert (labels[~(disc | extra | edge)] == 0).all()
    r = error_regions(img, truth, plate, face)
    assert list(r) == list(REGIONS)
    se = np.zeros((n, n))
    se[face] = 3 * 0.1 ** 2
    se[miss] = 3 * 0.6 ** 2
    se[extra] = 3 * 0.3 ** 2
    total = se.sum()
    for k, name in enumerate(REGIONS, start=1):
        assert r[name]["pixels"] == int((labels == k).sum())
        assert r[name]["error_share"] == pytest.approx(se[labels == k].sum() / total)
    assert sum(v["error_share"] for v in r.values()) == pytest.approx(1.0)
    assert r["face"]["psnr_composite"] == pytest.approx(10 * np.log10(0.8 ** 2 / 0.1 ** 2))
    assert error_regions(truth, truth, plate, face)["face"]["psnr_composite"] == float("inf")
