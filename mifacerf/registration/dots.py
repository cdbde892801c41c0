"""Dot detection (paper §4.1): a linear filter tuned to the yellow fiducials, and dot-strength maps.

The filter is linear in the diffuse proxy (:mod:`.proxies`): a colour projection ``w · rgb``
followed by a centre–surround (difference of Gaussians) kernel matched to the dot's image
size. Before the colour projection the proxy is divided by its local brightness (a wide
Gaussian of the luminance), so a dot in a dim, shadowed region responds like one in full
light; the kernel has zero mean, so smooth skin gives no response.

*Tuning* (:meth:`DotFilter.fit`), from the neutral expression and the user's template:

1. prior colour direction: a yellow ``(1, 0.9, 0.15)`` made orthogonal to the median face
   colour (so skin, whatever its shading, projects to zero);
2. positives: the strongest prior response within 2 pixels of every template fiducial
   projected into every camera where it is visible; negatives: face pixels farther than
   the dot spacing allows from every projected fiducial;
3. Fisher's linear discriminant ``w ∝ (Σ_neg + εI)⁻¹ (μ_pos − μ_neg)`` on brightness-normalised
   colours;
4. per camera, a scale so that the median dot peak of the neutral is 1 — a dot-strength
   of 1 per view is a typical, clearly seen dot.

The **dot-strength map** of a view is ``max(0, response) / scale``. A 3-D point's dot
strength (:mod:`.snap`) sums it over the views where the point is visible.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

PRIOR_YELLOW = np.array([1.0, 0.9, 0.15])


def luminance(img: np.ndarray) -> np.ndarray:
    from ..imageio import LUMINANCE

    return (img[..., :3] @ LUMINANCE.astype(np.float32)).astype(np.float32)


def gaussian(img: np.ndarray, sigma: float) -> np.ndarray:
    import cv2

    k = int(2 * np.ceil(3.5 * sigma) + 1)
    return cv2.GaussianBlur(np.asarray(img, np.float32), (k, k), sigma, sigmaY=sigma,
                            borderType=cv2.BORDER_REFLECT)


def face_mask(diffuse: np.ndarray, rel: float = 0.03) -> np.ndarray:
    """Pixels that see the subject (brightness above ``rel`` of the 99th percentile)."""
    lum = luminance(diffuse)
    ref = np.percentile(lum, 99.5)
    return lum > rel * max(ref, 1e-12)


@dataclass
class DotFilter:
    """The tuned filter. ``colour`` (3,); ``sigma`` centre / ``surround`` Gaussian (pixels);
    ``norm_sigma`` the brightness normalisation scale (pixels); ``scales`` per camera."""

    colour: np.ndarray
    sigma: float
    surround: float
    norm_sigma: float
    scales: dict = field(default_factory=dict)

    @staticmethod
    def sizes(dot_radius_px: float) -> tuple[float, float, float]:
        """Centre σ, surround σ and normalisation σ for a dot of ``dot_radius_px`` pixels."""
        sigma = float(np.sqrt((dot_radius_px / 2) ** 2 + 1 / 12 + 0.15))
        return sigma, 2.5 * sigma, 8.0 * sigma + 4.0

    def normalised(self, diffuse: np.ndarray) -> np.ndarray:
        lum = gaussian(luminance(diffuse), self.norm_sigma)
        floor = 0.02 * max(float(np.percentile(lum, 99.5)), 1e-12)
        return diffuse / np.maximum(lum, floor)[..., None]

    def response(self, diffuse: np.ndarray, colour: np.ndarray | None = None) -> np.ndarray:
        """The linear response (H, W) float32 (signed, unscaled)."""
        w = np.asarray(self.colour if colour is None else colour, np.float32)
        proj = (self.normalised(diffuse) @ w).astype(np.float32)
        return gaussian(proj, self.sigma) - gaussian(proj, self.surround)

    def strength(self, diffuse: np.ndarray, camera: str) -> np.ndarray:
        """The dot-strength map (H, W) float32 of one view."""
        s = self.scales.get(camera, np.median(list(self.scales.values())) if self.scales else 1.0)
        return (np.maximum(self.response(diffuse), 0.0) / np.float32(s)).astype(np.float32)

    # ------------------------------------------------------------------ tuning
    @classmethod
    def fit(cls, diffuse: dict, dots_uv: dict, dot_radius_px: float) -> "DotFilter":
        """Tune on the neutral: ``diffuse`` {camera: (H, W, 3)}; ``dots_uv`` {camera: (N, 2) pixels of
        the template's fiducials visible there}; ``dot_radius_px`` the dots' radius in pixels."""
        sigma, surround, norm_sigma = cls.sizes(dot_radius_px)
        probe = cls(PRIOR_YELLOW.copy(), sigma, surround, norm_sigma)
        pos, neg = [], []
        rng = np.random.default_rng(0)
        prior = None
        for cam, img in diffuse.items():
            mask = face_mask(img)
            if mask.sum() < 10:
                continue
            nimg = probe.normalised(img)
            if prior is None:
                skin = np.median(nimg[mask], axis=0)
                s = skin / np.linalg.norm(skin)
                prior = PRIOR_YELLOW - (PRIOR_YELLOW @ s) * s
                prior /= np.linalg.norm(prior)
            r = probe.response(img, prior)
            uv = np.asarray(dots_uv.get(cam, np.zeros((0, 2))), np.float64).reshape(-1, 2)
            uv = uv[np.isfinite(uv).all(1)]
            if len(uv):
                pk, _ = peak_near(r, uv, 2.0)
                ij = np.round(pk[:, ::-1]).astype(int)
                ok = (ij >= 0).all(1) & (ij[:, 0] < img.shape[0]) & (ij[:, 1] < img.shape[1])
                pos.append(nimg[ij[ok, 0], ij[ok, 1]])
            # negatives: face pixels away from every projected dot
            far = mask.copy()
            if len(uv):
                import cv2

                near = np.zeros(mask.shape, np.uint8)
                rad = int(np.ceil(2.5 * dot_radius_px + 3))
                for u, v in np.round(uv).astype(int):
                    cv2.circle(near, (int(u), int(v)), rad, 1, -1)
                far &= near == 0
            idx = np.flatnonzero(far.ravel())
            if len(idx) > 20000:
                idx = rng.choice(idx, 20000, replace=False)
            neg.append(nimg.reshape(-1, 3)[idx])
        if prior is None:
            raise ValueError("no camera sees the subject; cannot tune the dot filter")
        colour = prior
        if pos and sum(len(p) for p in pos) >= 5:
            P, N = np.concatenate(pos), np.concatenate(neg)
            cov = np.cov(N.T) + 1e-4 * np.trace(np.cov(N.T)) * np.eye(3)
            w = np.linalg.solve(cov, P.mean(0) - N.mean(0))
            w /= np.linalg.norm(w)
            if (P @ w).mean() > (N @ w).mean():
                colour = w
        f = cls(np.asarray(colour, np.float64), sigma, surround, norm_sigma)
        for cam, img in diffuse.items():
            uv = np.asarray(dots_uv.get(cam, np.zeros((0, 2))), np.float64).reshape(-1, 2)
            uv = uv[np.isfinite(uv).all(1)]
            if len(uv) == 0:
                continue
            _, val = peak_near(np.maximum(f.response(img), 0), uv, 2.0)
            val = val[val > 0]
            if len(val):
                f.scales[cam] = float(np.median(val))
        if not f.scales:
            raise ValueError("no template fiducial is visible in any view; cannot tune the dot filter")
        return f

    def to_dict(self) -> dict:
        return {"colour": [float(c) for c in self.colour], "sigma": self.sigma, "surround": self.surround,
                "norm_sigma": self.norm_sigma, "scales": self.scales}

    @classmethod
    def from_dict(cls, d: dict) -> "DotFilter":
        return cls(np.asarray(d["colour"], np.float64), float(d["sigma"]), float(d["surround"]),
                   float(d["norm_sigma"]), dict(d.get("scales", {})))


# --------------------------------------------------------------------------------- sampling
def bilinear(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of a 2-D map at pixel positions ``uv`` (..., 2); 0 outside or at NaN."""
    h, w = img.shape[:2]
    u, v = uv[..., 0], uv[..., 1]
    ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
    u = np.where(ok, u, 0.0)
    v = np.where(ok, v, 0.0)
    x0 = np.minimum(np.floor(u).astype(np.int64), w - 2) if w > 1 else np.zeros(u.shape, np.int64)
    y0 = np.minimum(np.floor(v).astype(np.int64), h - 2) if h > 1 else np.zeros(v.shape, np.int64)
    fx, fy = u - x0, v - y0
    flat = img.reshape(-1)
    i00 = y0 * w + x0
    out = (flat[i00] * (1 - fx) * (1 - fy) + flat[i00 + 1] * fx * (1 - fy)
           + flat[i00 + w] * (1 - fx) * fy + flat[i00 + w + 1] * fx * fy)
    return np.where(ok, out, 0.0)


def peak_near(img: np.ndarray, uv: np.ndarray, radius: float = 1.5,
              centroid_sigma: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Sub-pixel local maxima of a map near pixel positions ``uv`` (N, 2).

    The largest pixel within ``radius`` (a square window) of each position, refined by a
    separable parabola through its 3 × 3 neighbourhood; with ``centroid_sigma`` the position
    is then refined as the centroid of the (non-negative) map under a Gaussian window of that
    width, iterated (more accurate for blobs of a pixel or two). Returns (peaks (N, 2),
    values (N,)); NaN / 0 for positions outside the image.
    """
    h, w = img.shape
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    n = len(uv)
    ok = np.isfinite(uv).all(1)
    r = int(np.ceil(radius))
    c = np.where(ok[:, None], np.round(uv), 0).astype(np.int64)
    du, dv = np.meshgrid(np.arange(-r, r + 1), np.arange(-r, r + 1))
    du, dv = du.ravel(), dv.ravel()
    U = np.clip(c[:, :1] + du[None], 1, w - 2)
    V = np.clip(c[:, 1:] + dv[None], 1, h - 2)
    vals = img[V, U]
    k = np.argmax(vals, axis=1)
    pu, pv = U[np.arange(n), k], V[np.arange(n), k]
    f0 = img[pv, pu]
    fl, fr = img[pv, pu - 1], img[pv, pu + 1]
    fu, fd = img[pv - 1, pu], img[pv + 1, pu]

    def vertex(a, b, cc):
        den = a - 2 * b + cc
        with np.errstate(divide="ignore", invalid="ignore"):
            off = np.where(den < -1e-20, 0.5 * (a - cc) / den, 0.0)
        return np.clip(off, -0.5, 0.5)

    ou, ov = vertex(fl, f0, fr), vertex(fu, f0, fd)
    peaks = np.stack([pu + ou, pv + ov], 1).astype(np.float64)
    value = f0 - 0.25 * ((fl - fr) * ou + (fu - fd) * ov)
    inside = ok & (uv[:, 0] >= -0.5) & (uv[:, 1] >= -0.5) & (uv[:, 0] <= w - 0.5) & (uv[:, 1] <= h - 0.5)
    if centroid_sigma is not None and n:
        peaks = centroid(img, peaks, pu, pv, centroid_sigma)
    peaks[~inside] = np.nan
    value = np.where(inside, value, 0.0)
    return peaks, value


def centroid(img: np.ndarray, start: np.ndarray, pu: np.ndarray, pv: np.ndarray, sigma: float,
             iterations: int = 3) -> np.ndarray:
    """Gaussian-windowed centroids of ``max(img, 0)`` about integer peaks (pu, pv), starting at ``start``."""
    h, w = img.shape
    k = int(np.ceil(2.5 * sigma))
    du, dv = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1))
    U = np.clip(pu[:, None, None] + du[None], 0, w - 1)
    V = np.clip(pv[:, None, None] + dv[None], 0, h - 1)
    W = np.maximum(img[V, U], 0.0).astype(np.float64)
    W *= (U == pu[:, None, None] + du[None]) & (V == pv[:, None, None] + dv[None])  # nothing past the border
    c = start - np.stack([pu, pv], 1)
    for _ in range(iterations):
        g = np.exp(-((du[None] - c[:, :1, None]) ** 2 + (dv[None] - c[:, 1:, None]) ** 2) / (2 * sigma ** 2)) * W
        tot = g.sum((1, 2))
        good = tot > 1e-12
        cu = np.where(good, (g * du[None]).sum((1, 2)) / np.maximum(tot, 1e-300), c[:, 0])
        cv = np.where(good, (g * dv[None]).sum((1, 2)) / np.maximum(tot, 1e-300), c[:, 1])
        c = np.clip(np.stack([cu, cv], 1), -1.0, 1.0)
    return np.stack([pu, pv], 1) + c
