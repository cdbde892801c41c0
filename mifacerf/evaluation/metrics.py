"""Image error metrics on a mask. Images are linear sRGB (H, W, 3|4); masks (H, W) bool.

PSNR uses the reference's peak on the mask (``20 log10(max_ref / RMSE)``), so it does not
depend on the absolute exposure of a scene; RMSE is over all three channels.
"""
from __future__ import annotations

import numpy as np


def _check(a, b, mask):
    a = np.asarray(a, np.float64)[..., :3]
    b = np.asarray(b, np.float64)[..., :3]
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    mask = np.ones(a.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    if mask.shape != a.shape[:2]:
        raise ValueError(f"mask {mask.shape} does not match images {a.shape[:2]}")
    if not mask.any():
        raise ValueError("empty mask")
    return a, b, mask


def psnr(image, reference, mask=None) -> float:
    """PSNR in dB of ``image`` against ``reference`` on ``mask`` (peak: the reference's maximum there)."""
    a, b, mask = _check(image, reference, mask)
    mse = ((a - b)[mask] ** 2).mean()
    peak = b[mask].max()
    if mse == 0:
        return float("inf")
    return float(10 * np.log10(max(peak, 1e-30) ** 2 / mse))


def psnr_two_truths(image, truth_a, truth_b, mask=None) -> dict:
    """PSNR of ``image`` against a Monte Carlo truth rendered as two independent halves.

    The truth is ``t = (a + b) / 2``; its noise variance per value is ``E[(a − b)²] / 4``, so
    ``MSE(image, t) − mean((a − b)²) / 4`` is an unbiased estimate of the MSE against the
    truth's expectation (the noise-free image). Returns ``psnr`` (against ``t``),
    ``noise_floor`` (PSNR of ``t`` itself against its expectation) and ``psnr_noise_corrected``
    (``inf`` when the estimated error is not above the noise); all share the peak of ``t``.
    """
    a, b, mask = _check(truth_a, truth_b, mask)
    img, _, _ = _check(image, truth_a, mask)
    t = 0.5 * (a + b)
    peak2 = max(t[mask].max(), 1e-30) ** 2
    mse = ((img - t)[mask] ** 2).mean()
    noise = ((a - b)[mask] ** 2).mean() / 4
    db = lambda m: float(10 * np.log10(peak2 / m)) if m > 0 else float("inf")  # noqa: E731
    return {"psnr": db(mse), "noise_floor": db(noise), "psnr_noise_corrected": db(mse - noise)}


def summary(values) -> dict:
    v = np.asarray([x for x in values if np.isfinite(x)], np.float64)
    if not len(v):
        return {"n": 0}
    return {"n": int(len(v)), "mean": float(v.mean()), "min": float(v.min()), "median": float(np.median(v)),
            "max": float(v.max())}


# What the user sees: the render and the truth composited over the same plate, and their coverage.
# Both images are premultiplied RGBA (rgb already carries alpha, as the renderer and the truth give them).

def over(rgba, plate) -> np.ndarray:
    """Premultiplied RGBA (H, W, 4) over a plate (H, W, 3): ``rgb + (1 - alpha) plate``, float64."""
    rgba = np.asarray(rgba, np.float64)
    return rgba[..., :3] + (1.0 - rgba[..., 3:4]) * np.asarray(plate, np.float64)[..., :3]


def composite_psnr(image, truth, plate, coverage: float = 1e-3) -> float:
    """PSNR of ``image`` over ``plate`` against ``truth`` over the same plate, on every pixel where
    either has alpha above ``coverage``: a pixel the model misses (or adds) shows the plate in one
    composite and the subject in the other, so it counts as error. Peak: the truth composite's
    maximum there. ``inf`` for identical composites."""
    image, truth = np.asarray(image), np.asarray(truth)
    if image.shape[-1] != 4 or truth.shape[-1] != 4:
        raise ValueError("composite_psnr needs premultiplied RGBA images")
    mask = (image[..., 3] > coverage) | (truth[..., 3] > coverage)
    return psnr(over(image, plate), over(truth, plate), mask)


def composite_psnr_two_truths(image, truth_a, truth_b, plate, coverage: float = 1e-3) -> dict:
    """:func:`composite_psnr` against a Monte Carlo truth rendered as two independent halves (its mean the
    truth), with the truth's own noise taken out as in :func:`psnr_two_truths` (the composites over the
    plate; scored where the render or the mean truth has alpha above ``coverage``): ``psnr`` (= the plain
    composite PSNR), ``noise_floor``, ``psnr_noise_corrected``."""
    image, a, b = np.asarray(image), np.asarray(truth_a), np.asarray(truth_b)
    if image.shape[-1] != 4 or a.shape[-1] != 4 or b.shape[-1] != 4:
        raise ValueError("composite_psnr_two_truths needs premultiplied RGBA images")
    t = 0.5 * (a.astype(np.float64) + b)
    mask = (image[..., 3] > coverage) | (t[..., 3] > coverage)
    return psnr_two_truths(over(image, plate), over(a, plate), over(b, plate), mask)


def silhouette_iou(alpha, truth_alpha) -> float:
    """Soft intersection over union of two coverages in [0, 1]: ``Σ min(a, t) / Σ max(a, t)``
    (binary masks give the usual IoU; anti-aliased edges count by their coverage)."""
    a = np.clip(np.asarray(alpha, np.float64), 0, 1)
    t = np.clip(np.asarray(truth_alpha, np.float64), 0, 1)
    union = np.maximum(a, t).sum()
    if union == 0:
        raise ValueError("both coverages are empty")
    return float(np.minimum(a, t).sum() / union)


def uncovered(alpha, truth_alpha, threshold: float = 0.5) -> tuple[float, np.ndarray]:
    """The truth's foreground (alpha > ``threshold``) that the model does not cover (its alpha
    ≤ ``threshold``): (share of the truth's foreground pixels, (H, W) bool map of them)."""
    fg = np.asarray(truth_alpha) > threshold
    if not fg.any():
        raise ValueError("the truth has no foreground")
    miss = fg & ~(np.asarray(alpha) > threshold)
    return float(miss.sum() / fg.sum()), miss


def coverage_picture(alpha, truth_alpha, threshold: float = 0.5) -> np.ndarray:
    """(H, W, 3) linear RGB: grey where both cover, red where only the truth does (the model misses
    it), blue where only the model does (extra), black where neither."""
    a = np.asarray(alpha) > threshold
    t = np.asarray(truth_alpha) > threshold
    pic = np.zeros(a.shape + (3,), np.float32)
    pic[a & t] = 0.25
    pic[t & ~a] = (1.0, 0.0, 0.0)
    pic[a & ~t] = (0.0, 0.2, 1.0)
    return pic


#: where a composite's error sits: the order of :func:`error_regions`' labels (0 = not scored)
REGIONS = ("face", "extension", "silhouette", "extra")


def region_map(alpha, truth_alpha, face, threshold: float = 0.5, band: int = 1,
               coverage: float = 1e-3) -> np.ndarray:
    """(H, W) int labels of the pixels a composite is scored on (either alpha above ``coverage``):

    1 **face** — the face mask ``face`` (H, W) bool, the template's skin, eyes and teeth in the truth;
    2 **extension** — the rest of the truth's foreground (alpha > ``threshold``): scalp, hair, ears, neck,
    the back of the head, whatever the model covers of them;
    3 **silhouette** — within ``band`` pixels (3 x 3 steps) of the truth's or the render's outline (a pixel
    whose alpha crosses ``threshold`` against a neighbour's, or is partial);
    4 **extra** — the render's coverage outside the truth's foreground, away from the outline;
    0 elsewhere. The silhouette band takes precedence over face and extension.
    """
    from scipy.ndimage import binary_dilation

    a = np.asarray(alpha, np.float64)
    t = np.asarray(truth_alpha, np.float64)
    scored = (a > coverage) | (t > coverage)
    edge = np.zeros(a.shape, bool)
    for x in (a, t):
        fg = x > threshold
        edge |= (binary_dilation(fg) & ~fg) | (binary_dilation(~fg) & fg) | ((x > coverage) & (x < 1 - coverage))
    if band > 1:
        edge = binary_dilation(edge, iterations=band - 1)
    out = np.zeros(a.shape, np.int8)
    out[scored & ~(t > threshold)] = 4
    out[scored & (t > threshold)] = 2
    out[scored & (t > threshold) & np.asarray(face, bool)] = 1
    out[scored & edge] = 3
    return out


def error_regions(image, truth, plate, face, threshold: float = 0.5, band: int = 1) -> dict:
    """Where the composite error sits: for each of :data:`REGIONS` (:func:`region_map`), its pixels, its
    share of the composite's squared error (the shares sum to 1 over the scored pixels) and the composite
    PSNR on it (the peak of the whole scored truth composite, so the numbers compare)."""
    image, truth = np.asarray(image), np.asarray(truth)
    labels = region_map(image[..., 3], truth[..., 3], face, threshold, band)
    a, b = over(image, plate), over(truth, plate)
    se = ((a - b) ** 2).sum(axis=-1)
    scored = labels > 0
    if not scored.any():
        raise ValueError("nothing to score: both coverages are empty")
    total = se[scored].sum()
    peak2 = max(b[scored].max(), 1e-30) ** 2
    out = {}
    for k, name in enumerate(REGIONS, start=1):
        sel = labels == k
        n = int(sel.sum())
        mse = se[sel].sum() / (3 * n) if n else 0.0
        out[name] = {"pixels": n, "error_share": float(se[sel].sum() / total) if total > 0 else 0.0,
                     "psnr_composite": float(10 * np.log10(peak2 / mse)) if mse > 0 else float("inf")}
    return out
