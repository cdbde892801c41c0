"""The render's alpha is the target geometry's anti-aliased pixel coverage (issue 16 item 2), checked
against the exact coverage of a convex mesh's outline, and the colour of hits no field covers comes from
the nearest covered pixel (:func:`mifacerf.rendering.frame.resolve_pixels`)."""
import numpy as np
import pytest

from rendering.conftest import toy_model  # noqa: F401  (the built toy model fixture, shared)


def _clip(poly, axis, value, keep_below):
    """Sutherland–Hodgman: the part of convex polygon ``poly`` (K, 2) on one side of x[axis] = value."""
    out = []
    for k in range(len(poly)):
        p, q = poly[k], poly[(k + 1) % len(poly)]
        pin = p[axis] <= value if keep_below else p[axis] >= value
        qin = q[axis] <= value if keep_below else q[axis] >= value
        if pin:
            out.append(p)
        if pin != qin:
            t = (value - p[axis]) / (q[axis] - p[axis])
            out.append(p + t * (q - p))
    return np.array(out).reshape(-1, 2)


def _area(poly):
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def exact_coverage(outline, height, width):
    """(H, W) area of convex polygon ``outline`` (pixel coordinates) inside each pixel's square
    ``[j-0.5, j+0.5] x [i-0.5, i+0.5]``."""
    cov = np.zeros((height, width))
    lo = np.floor(outline.min(axis=0) - 0.5).astype(int)
    hi = np.ceil(outline.max(axis=0) + 0.5).astype(int)
    for i in range(max(lo[1], 0), min(hi[1] + 1, height)):
        for j in range(max(lo[0], 0), min(hi[0] + 1, width)):
            p = outline
            for axis, value, below in ((0, j - 0.5, False), (0, j + 0.5, True), (1, i - 0.5, False),
                                       (1, i + 0.5, True)):
                p = _clip(p, axis, value, below)
                if not len(p):
                    break
            cov[i, j] = _area(p)
    return cov


def test_alpha_is_the_exact_coverage_of_the_outline(toy_model):
    """The toy head is a convex mesh (an icosphere on an ellipsoid): its outline in a pinhole camera is
    the convex hull of its projected vertices, so every pixel's exact coverage is known. Seen from above
    and behind, much of it is outside every field: the old alpha (field coverage) had holes there."""
    from scipy.spatial import ConvexHull

    from mifacerf import environment as E
    from mifacerf.camera import Camera
    from mifacerf.rendering.renderer import Renderer, RenderStats, RenderWarning

    model = toy_model
    cam = Camera.look_at("above", [0.25, 0.9, -0.6], [0, 0, 0], width=40, height=40, focal=150.0)
    W = np.zeros((model.n_vertices, len(model.expressions)))
    W[:, model.expression_index("neutral")] = 1.0
    stats = RenderStats()
    renderer = Renderer(model)
    with pytest.warns(RenderWarning, match="from the nearest capture camera"):  # 111 deg: beyond the fields
        img = renderer.render(model.vertices[0], W, cam, E.generated("sky", 32), spp=64, stats=stats)
    traced = renderer._traced(model.vertices[0])     # the traced target (frame.ChordOffset; the toy's, unmoved)
    uv, z = cam.project(traced)
    assert (z > 0).all()
    outline = uv[ConvexHull(uv).vertices]
    exact = exact_coverage(outline, cam.height, cam.width)
    alpha = img[..., 3].astype(np.float64)
    edge = (exact > 1e-6) & (exact < 1 - 1e-6)
    assert edge.sum() > 40
    err = np.abs(alpha - exact)
    # 64 jittered stratified samples: a straight edge crosses about 8 of the 8 x 8 strata
    assert err[edge].mean() < 0.03, err[edge].mean()
    assert err[edge].max() < 0.1, err[edge].max()
    assert err[exact == 0].max() == 0 and err[exact >= 1 - 1e-9].max() == 0
    # parts of the head no field covers are hit and filled, not holes
    assert stats.unseen_samples > 0 and stats.filled_pixels > 0
    fg = alpha > 0
    assert (img[..., :3][fg].sum(axis=-1) > 0).all()
    np.testing.assert_allclose(img[..., 3].sum(), exact.sum(), rtol=0.01)


def test_resolve_pixels_fills_from_the_nearest_covered_pixel():
    from mifacerf.rendering.frame import resolve_pixels

    # a 1 x 4 frame, 2 samples per pixel: pixel 0 both covered, pixel 1 one covered and one hit without
    # coverage, pixel 2 hit without coverage (nearest covered pixel: 1), pixel 3 missed
    pix = np.array([0, 0, 1, 1, 2])
    colour = np.array([[1, 0, 0], [0, 1, 0], [0, 0, 4], [9, 9, 9], [9, 9, 9]], np.float64)
    covered = np.array([True, True, True, False, False])
    img, filled = resolve_pixels(pix, colour, covered, 1, 4, 2)
    np.testing.assert_allclose(img[0, :, 3], [1, 1, 0.5, 0])
    np.testing.assert_allclose(img[0, 0, :3], [0.5, 0.5, 0])          # exactly the box filter of its samples
    np.testing.assert_allclose(img[0, 1, :3], [0, 0, 4])              # the uncovered sample takes the pixel's mean
    np.testing.assert_allclose(img[0, 2, :3], [0, 0, 2])              # pixel 1's colour, alpha 0.5
    np.testing.assert_array_equal(img[0, 3], 0)
    assert filled == 1
    # nothing covered anywhere: the hits keep their alpha, black
    img, filled = resolve_pixels(pix, colour, np.zeros(5, bool), 1, 4, 2)
    np.testing.assert_allclose(img[0, :, 3], [1, 1, 0.5, 0])
    assert img[..., :3].max() == 0 and filled == 0


@pytest.mark.parametrize("seed", range(6))
def test_the_fill_over_the_gaps_window_is_the_whole_images_bit_for_bit(seed):
    """resolve_pixels smooths the covered colours over the gap's bounding box grown by the Gaussian's radius
    only: the filled pixels are those of the normalised convolution over the whole image (``window=False``),
    bit for bit, for gaps anywhere (at the border, in the middle, several far apart, one pixel)."""
    from mifacerf.rendering import frame

    rng = np.random.default_rng(seed)
    H, W, spp = 96, 120, 2
    n = H * W
    pix = np.repeat(np.arange(n), spp)
    keep = rng.random(len(pix)) < 0.85                                   # some pixels missed, some half
    pix = pix[keep]
    colour = rng.random((len(pix), 3))
    covered = np.ones(len(pix), bool)
    yy, xx = np.divmod(pix, W)
    for k in range(seed % 3 + 1):      # gaps without coverage; the last of seed 2 and 5 beyond the Gaussian's reach
        cy, cx, r = rng.integers(0, H), rng.integers(0, W), (40 if seed % 3 == 2 and k == 2 else rng.integers(0, 12))
        covered &= (yy - cy) ** 2 + (xx - cx) ** 2 > r * r
    img, filled = frame.resolve_pixels(pix, colour, covered, H, W, spp)
    whole, filled_whole = frame.resolve_pixels(pix, colour, covered, H, W, spp, window=False)
    assert filled > 0 and filled == filled_whole
    np.testing.assert_array_equal(img, whole)
    np.testing.assert_array_equal(img, _fill_over_the_whole_image(pix, colour, covered, H, W, spp))


def _fill_over_the_whole_image(pix, colour, covered, H, W, spp):
    """resolve_pixels' rule written plainly (as it was before 2026-12-03): every gap pixel first takes the
    nearest covered pixel's colour (distance transform), then, where the Gaussian of the covered pixels
    reaches it, their normalised convolution over the whole image."""
    from scipy.ndimage import distance_transform_edt, gaussian_filter

    from mifacerf.rendering.frame import FILL_SIGMA

    n = H * W
    hits = np.bincount(pix, minlength=n).astype(np.float64)
    count = np.bincount(pix, weights=covered.astype(np.float64), minlength=n)
    total = np.stack([np.bincount(pix, weights=np.where(covered, colour[:, ch], 0.0), minlength=n) for ch in range(3)], -1)
    mean = total / np.maximum(count, 1.0)[:, None]
    empty = (hits > 0) & (count == 0)
    _, (ii, jj) = distance_transform_edt((count == 0).reshape(H, W), return_indices=True)
    mean[empty] = mean[(ii * W + jj).reshape(-1)[empty]]
    sigma = FILL_SIGMA * max(H, W)
    wsum = gaussian_filter((count > 0).reshape(H, W).astype(np.float64), sigma, mode="constant").reshape(-1)[empty]
    smooth = np.stack([gaussian_filter(np.where(count > 0, mean[:, ch], 0.0).reshape(H, W), sigma,
                                       mode="constant").reshape(-1)[empty] for ch in range(3)], -1)
    mean[empty] = np.where((wsum > 1e-3)[:, None], smooth / np.maximum(wsum, 1e-30)[:, None], mean[empty])
    rgba = np.empty((n, 4))
    rgba[:, :3] = (total + (hits - count)[:, None] * mean) / spp
    rgba[:, 3] = hits / spp
    return rgba.reshape(H, W, 4).astype(np.float32)


def test_outline_texels_are_the_outer_ring_not_the_rim_of_a_hole():
    """A field's texels beside the background (the texel-free area reaching the image border) are on the
    subject's outline and are marked (coverage -1: read only where the chunk has no other texel for the
    point); those around an enclosed opening (an eye, the mouth) are not."""
    from mifacerf.rendering.frame import mark_outline, outline_texels

    yy, xx = np.mgrid[:21, :21]
    r = np.hypot(yy - 10, xx - 10)
    depth = np.where((r <= 8) & (r > 2), 1.0, np.inf).astype(np.float32)
    edge = outline_texels(depth)
    seen = np.isfinite(depth)
    assert edge.any() and not (edge & ~seen).any()
    assert edge[r > 6.5].sum() == edge.sum()          # only the outer ring
    assert not edge[(r > 2) & (r < 4)].any()          # the hole's rim is kept
    img = np.ones((21, 21, 4), np.float32)
    out = mark_outline(img, depth)
    assert (out[edge, 3] == -1).all() and (out[~edge] == 1).all() and (out[..., :3] == 1).all() and (img == 1).all()
    assert (mark_outline(img, depth, mark=False) == 1).all()
    assert not outline_texels(np.full((5, 5), np.inf)).any() and not outline_texels(np.ones((5, 5))).any()
