"""Dot filter, strength maps and sub-pixel peaks on synthetic images with known dots."""
import numpy as np
import pytest

from mifacerf.registration.dots import DotFilter, bilinear, peak_near

SKIN = np.array([0.55, 0.36, 0.28])
YELLOW = np.array([0.85, 0.80, 0.12])


def blob_image(centres, radius, shape=(96, 96), shade=True, ss=8):
    """Skin with shading and yellow discs of ``radius`` pixels (supersampled coverage)."""
    h, w = shape
    o = (np.arange(ss) + 0.5) / ss - 0.5
    yy, xx = np.mgrid[0:h, 0:w]
    cover = np.zeros((h, w))
    for cu, cv in centres:
        d2 = ((xx[..., None, None] + o[None, None, :, None] - cu) ** 2
              + (yy[..., None, None] + o[None, None, None, :] - cv) ** 2)
        cover = np.maximum(cover, (d2 <= radius ** 2).mean((-1, -2)))
    s = (0.35 + 0.65 * np.clip(1 - ((xx - w / 2) ** 2 + (yy - h / 2) ** 2) / (0.55 * w) ** 2, 0, 1)) if shade \
        else np.ones((h, w))
    return (s[..., None] * (SKIN * (1 - cover[..., None]) + YELLOW * cover[..., None])).astype(np.float32)


@pytest.fixture(scope="module")
def scene(rng=np.random.default_rng(3)):
    c = np.stack(np.meshgrid(np.arange(12, 90, 9.0), np.arange(12, 90, 9.0)), -1).reshape(-1, 2)
    c = c + rng.uniform(-0.5, 0.5, c.shape)
    return c, blob_image(c, 1.4)


def test_bilinear_is_exact_on_planes():
    img = np.add.outer(np.arange(10.0) * 2, np.arange(12.0) * 3)
    uv = np.array([[3.25, 4.5], [0.0, 0.0], [10.9, 8.2], [-1, 2], [np.nan, 1]])
    got = bilinear(img, uv)
    np.testing.assert_allclose(got[:3], 3 * uv[:3, 0] + 2 * uv[:3, 1])
    assert got[3] == 0 and got[4] == 0


def test_peaks_are_sub_pixel(rng):
    yy, xx = np.mgrid[0:40, 0:40]
    c = rng.uniform(15, 25, (20, 2))
    for sigma in (0.8, 1.5):
        errs_q, errs_c = [], []
        for cu, cv in c:
            img = np.exp(-((xx - cu) ** 2 + (yy - cv) ** 2) / (2 * sigma ** 2))
            pq, vq = peak_near(img, np.array([[cu + 0.7, cv - 0.6]]), 1.5)
            pc, _ = peak_near(img, np.array([[cu + 0.7, cv - 0.6]]), 1.5, centroid_sigma=1.5 * sigma)
            errs_q.append(np.linalg.norm(pq[0] - [cu, cv]))
            errs_c.append(np.linalg.norm(pc[0] - [cu, cv]))
            assert vq[0] == pytest.approx(1.0, abs=0.15)   # a parabola under-reads a narrow peak
        assert max(errs_q) < 0.15 and max(errs_c) < 0.05


def test_filter_is_tuned_to_the_dots(scene):
    c, img = scene
    clicks = c + np.random.default_rng(0).normal(0, 0.7, c.shape)   # the user's ~1 px template
    f = DotFilter.fit({"cam": img}, {"cam": clicks}, 1.4)
    # skin of any brightness projects to ~0; yellow responds
    w = f.colour / np.linalg.norm(f.colour)
    assert abs(w @ SKIN) / np.linalg.norm(SKIN) < 0.1 and w @ YELLOW > 0.3
    s = f.strength(img, "cam")
    _, at_dots = peak_near(s, c, 1.0)
    assert np.median(at_dots) == pytest.approx(1.0, abs=0.05)
    far = np.ones(s.shape, bool)
    for u, v in c:
        far[max(0, int(v) - 4):int(v) + 5, max(0, int(u) - 4):int(u) + 5] = False
    assert np.percentile(s[far], 99.5) < 0.1
    # dim dots (a shadowed region) respond like bright ones: brightness is normalised locally
    s2 = f.strength(0.2 * img, "cam")
    np.testing.assert_allclose(peak_near(s2, c, 1.0)[1], at_dots, rtol=0.05)
    # round trip through the registration folder's JSON
    g = DotFilter.from_dict(f.to_dict())
    np.testing.assert_allclose(g.strength(img, "cam"), s)


def test_filter_needs_the_subject():
    with pytest.raises(ValueError):
        DotFilter.fit({"cam": np.zeros((32, 32, 3), np.float32)}, {"cam": np.zeros((0, 2))}, 1.0)
