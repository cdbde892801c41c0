"""Subject-motion check of a take: the paper's "sum of a representative sampling of the
captured frames" (§2.1), and how sharp it is.

Each camera sums a representative sample of its frames (lights spread evenly over
the arm's positions and strobes, :func:`representative_lights`). If the subject
moved during the 8 s of the sequence, fine detail (pores, the fiducial dots) lands
in different places in different frames and the sum is blurred; a still subject
gives a sum as sharp as its frames. Sharpness measures, chosen by name
(:data:`SHARPNESS_METHODS`):

* ``"laplacian"`` (default): variance of the Laplacian of the sum's luminance over
  its squared mean (scale-free: exposure does not change it);
* ``"highfreq"``: fraction of the sum's spectral energy above a quarter of Nyquist;
* ``"coherence"``: ``‖Σ ∇²I_k‖ / Σ ‖∇²I_k‖`` over the sampled frames — 1 when all
  frames' edges coincide, lower when they are displaced; needs no reference but
  depends on how different the sampled lights are.

The score of the sum means little on its own (it depends on the face and the lens),
so a take is judged against a **reference** for the same camera and the same light
sample: the median score of the session's accepted takes (a session starts by
taking its first expression twice and using the sharper take, see
:mod:`mifacerf.capture.session`). A take is blurred when, for any camera,
``score < threshold * reference``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..methods import lookup


def representative_lights(n_positions: int, n_strobes: int, k: int = 32, lights=None) -> np.ndarray:
    """About ``k`` light indices spread over the stage: every arm position, strobes staggered.

    With ``lights`` (the indices captured), the sample is drawn from those only.
    """
    n = n_positions * n_strobes
    pool = np.arange(n) if lights is None else np.unique(np.asarray(lights, np.int64))
    if len(pool) <= k:
        return pool
    # a golden-ratio walk over (position, strobe) so the sample covers both evenly
    per_pos = max(1, int(round(k / n_positions)))
    chosen = []
    g = 0.6180339887498949
    for j in range(n_positions):
        for m in range(per_pos):
            s = int(((j * per_pos + m) * g % 1.0) * n_strobes)
            chosen.append(j * n_strobes + s)
    chosen = np.array(sorted(set(chosen)), np.int64)
    chosen = chosen[np.isin(chosen, pool)]
    if len(chosen) < k // 2:  # a partial pool: fall back to an even spread over what exists
        chosen = pool[np.linspace(0, len(pool) - 1, k).round().astype(int)]
    return np.unique(chosen)


def _luminance(image: np.ndarray) -> np.ndarray:
    """Luminance (H, W) of (H, W[, C]); non-finite pixels (never written by a session) count as 0."""
    img = np.nan_to_num(np.asarray(image, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if img.ndim == 3:
        img = img @ np.array([0.2126, 0.7152, 0.0722])[: img.shape[2]] if img.shape[2] == 3 else img.mean(-1)
    return img


def _laplacian(g: np.ndarray) -> np.ndarray:
    p = np.pad(g, 1, mode="edge")
    return p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:] - 4 * g


def laplacian_sharpness(image: np.ndarray) -> float:
    """Variance of the Laplacian of the luminance over the squared mean luminance (H, W[, 3]) -> float."""
    g = _luminance(image)
    m = g.mean()
    if not np.isfinite(m) or m <= 0:
        return 0.0
    return float(_laplacian(g).var() / m**2)


def highfreq_sharpness(image: np.ndarray, cutoff: float = 0.25) -> float:
    """Fraction of the (mean-removed) luminance spectrum's energy above ``cutoff`` x Nyquist."""
    g = _luminance(image)
    g = g - g.mean()
    F = np.abs(np.fft.rfft2(g)) ** 2
    fy = np.fft.fftfreq(g.shape[0])[:, None]
    fx = np.fft.rfftfreq(g.shape[1])[None, :]
    r = np.sqrt(fx**2 + fy**2) / 0.5
    total = F.sum()
    return float(F[r > cutoff].sum() / total) if total > 0 else 0.0


def coherence(frames) -> float:
    """``‖Σ_k ∇²I_k‖ / Σ_k ‖∇²I_k‖`` over frames (K, H, W[, 3]); 1 = perfectly aligned edges."""
    laps = [_laplacian(_luminance(f)) for f in frames]
    den = sum(np.linalg.norm(l) for l in laps)
    return float(np.linalg.norm(sum(laps)) / den) if den > 0 else 0.0


#: name -> f(sum image, frames) -> score (higher = sharper); the first is the default
SHARPNESS_METHODS = {
    "laplacian": lambda total, frames: laplacian_sharpness(total),
    "highfreq": lambda total, frames: highfreq_sharpness(total),
    "coherence": lambda total, frames: coherence(frames),
}


DEFAULT_SHARPNESS_METHOD = "laplacian"


def take_score(frames, method: str = DEFAULT_SHARPNESS_METHOD) -> float:
    """Sharpness of the sum of ``frames`` (K, H, W, 3) by ``method`` (:data:`SHARPNESS_METHODS`)."""
    fn = lookup(SHARPNESS_METHODS, method, "sharpness")
    frames = np.asarray(frames, np.float32)
    if frames.ndim != 4 or frames.shape[0] == 0:
        raise ValueError(f"expected frames (K, H, W, C) with K >= 1, got shape {frames.shape}")
    return fn(frames.sum(axis=0, dtype=np.float64), frames)


@dataclass
class MotionVerdict:
    """Per camera: ``scores``, the ``reference`` used (None: none yet), ``ratios``; ``blurred``."""

    scores: dict[str, float]
    reference: dict[str, float | None]
    threshold: float
    ratios: dict[str, float | None] = field(default_factory=dict)

    @property
    def blurred_cameras(self) -> list[str]:
        return [c for c, r in self.ratios.items() if r is not None and r < self.threshold]

    @property
    def blurred(self) -> bool:
        return bool(self.blurred_cameras)

    def to_dict(self) -> dict:
        return {"scores": self.scores, "reference": self.reference, "ratios": self.ratios,
                "threshold": self.threshold, "blurred": self.blurred}


@dataclass
class MotionCheck:
    """Judge takes: ``sample`` lights per sum, ``method`` (see :data:`SHARPNESS_METHODS`),
    ``threshold`` on score / reference."""

    sample: int = 32
    method: str = DEFAULT_SHARPNESS_METHOD
    threshold: float = 0.7

    def __post_init__(self):
        lookup(SHARPNESS_METHODS, self.method, "sharpness")
        if not 0 < self.threshold <= 1:
            raise ValueError(f"threshold must lie in (0, 1], got {self.threshold}")

    def scores(self, frames_by_camera: dict[str, np.ndarray]) -> dict[str, float]:
        """Score per camera from its sampled frames (K, H, W, 3)."""
        return {c: take_score(f, self.method) for c, f in frames_by_camera.items()}

    def judge(self, scores: dict[str, float], reference: dict[str, float] | None) -> MotionVerdict:
        reference = reference or {}
        ref = {c: reference.get(c) for c in scores}
        ratios = {c: (None if not ref[c] else scores[c] / ref[c]) for c in scores}
        return MotionVerdict(scores, ref, self.threshold, ratios)


def reference_from(accepted: list[dict[str, float]]) -> dict[str, float]:
    """Per camera: the median score over the accepted takes' score dicts."""
    cams = sorted({c for s in accepted for c in s})
    return {c: float(np.median([s[c] for s in accepted if c in s])) for c in cams}
