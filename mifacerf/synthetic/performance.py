"""A scripted facial performance of the synthetic subject (the trajectory, not the images).

:func:`script` turns a length in seconds into a parameter vector per video frame over the
subject's controls (:attr:`Subject.controls`). It is built from the layers an actor's
performance has, each with its own timing, summed and clipped to the controls' ranges:

* **lead-in**: the first :data:`LEAD_IN` seconds are the neutral face at the neutral head pose
  (the actor is told to start at rest; tracking is initialised there, as with a mocap T-pose);
* **speech**: a sequence of visemes (:data:`VISEMES`, 70–160 ms each, grouped in words with
  short pauses), co-articulated with a dominance model (Cohen & Massaro 1993): every viseme's
  target is weighted by a Gaussian dominance about its centre, the weights normalised against a
  rest dominance, so the mouth glides between targets and never holds a shape; every target's
  amplitude is jittered ±25 %;
* **emotions** coming and going (:data:`EMOTIONS`: asymmetric smirk, worry, joy, scepticism —
  none of them a captured preset): attack 0.2–0.3 s, hold 0.15–0.4 s, release 0.25–0.4 s, one
  after the other, added on top of the speech;
* **head motion**: yaw, pitch and roll as sums of slow sinusoids with random phases plus a nod,
  faded in after the lead-in;
* **blinks** every 0.8–2 s (closing 70 ms, opening 130 ms, sometimes a half blink) and
  **saccades** of the gaze every 0.4–0.9 s (40 ms transitions).

Because the layers are summed with independent timing (a smirk while saying /oo/, a blink during
a nod), almost no frame is a convex blend of the captured expressions
(:func:`blend_residual` measures it).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LEAD_IN = 0.20  #: seconds of neutral rest at the start

#: viseme targets (control values); none equals a captured preset
VISEMES: dict[str, dict[str, float]] = {
    "AA": {"jaw_open": 0.22, "lower_lip_down": 0.25, "upper_lip_raise": 0.12},
    "AE": {"jaw_open": 0.15, "mouth_stretch": 0.35, "upper_lip_raise": 0.15},
    "EE": {"mouth_stretch": 0.6, "smile_L": 0.25, "smile_R": 0.25, "jaw_open": 0.05},
    "IH": {"jaw_open": 0.08, "mouth_stretch": 0.3},
    "OH": {"jaw_open": 0.17, "pucker": 0.45, "funnel": 0.45},
    "OO": {"pucker": 0.85, "funnel": 0.5, "jaw_open": 0.06},
    "MBP": {"lips_press": 0.9},
    "FV": {"lower_lip_tuck": 0.85, "upper_lip_raise": 0.2, "jaw_open": 0.02},
    "TDS": {"jaw_open": 0.05, "mouth_stretch": 0.3, "upper_lip_raise": 0.2, "lower_lip_down": 0.25},
    "L": {"jaw_open": 0.12, "upper_lip_raise": 0.08},
    "W": {"pucker": 0.7, "funnel": 0.25, "jaw_open": 0.03},
    "SH": {"funnel": 0.85, "pucker": 0.3, "jaw_open": 0.04},
    "KG": {"jaw_open": 0.13, "mouth_stretch": 0.15},
}

#: words as viseme sequences (a small vocabulary; the script strings them together)
WORDS = [
    ("hello", ["KG", "AE", "L", "OH"]), ("world", ["W", "OH", "L", "TDS"]),
    ("maybe", ["MBP", "AE", "MBP", "EE"]), ("five", ["FV", "AA", "FV"]),
    ("shoe", ["SH", "OO"]), ("people", ["MBP", "EE", "MBP", "L"]), ("water", ["W", "AA", "TDS", "IH"]),
    ("believe", ["MBP", "IH", "L", "EE", "FV"]), ("food", ["FV", "OO", "TDS"]), ("cheese", ["SH", "EE", "TDS"]),
]

#: emotions: control offsets added on top of the speech (asymmetric / mixed: out of the captured set)
EMOTIONS: dict[str, dict[str, float]] = {
    "smirk": {"smile_L": 0.7, "cheek_raise_L": 0.4, "brow_raise_R": 0.5},
    "worry": {"brow_raise_L": 0.6, "brow_raise_R": 0.6, "frown": 0.6, "lip_corner_down": 0.4},
    "joy": {"smile_L": 0.8, "smile_R": 0.75, "cheek_raise_L": 0.5, "cheek_raise_R": 0.5, "eyes_wide": 0.25},
    "sceptic": {"brow_lower_L": 0.6, "brow_raise_R": 0.45, "lip_corner_down": 0.3, "nose_wrinkle": 0.2},
}


@dataclass
class Script:
    """A scripted performance: ``params`` (N, P) per frame, ``fps``, and the ``events`` that made it
    (for the record: visemes, emotions, blinks, saccades with their times in seconds)."""

    params: np.ndarray
    fps: float
    control_names: list
    events: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return len(self.params)

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.fps

    def control(self, name: str) -> np.ndarray:
        return self.params[:, self.control_names.index(name)]


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3 - 2 * x)


def _envelope(t, start, attack, hold, release):
    """0 → 1 over ``attack`` from ``start``, 1 for ``hold``, → 0 over ``release`` (C¹ smooth)."""
    up = _smoothstep((t - start) / attack)
    down = 1.0 - _smoothstep((t - start - attack - hold) / release)
    return up * down


def _blink_profile(t, start, close=0.07, open_=0.13, depth=1.0):
    a = _smoothstep((t - start) / close)
    b = 1.0 - _smoothstep((t - start - close) / open_)
    return depth * np.where(t < start + close, a, b) * (t >= start)


def script(seconds: float, fps: float = 60.0, seed: int = 0, control_names=None, controls=None) -> Script:
    """The scripted trajectory over ``seconds`` at ``fps`` (see the module docstring).

    ``controls``: the subject's :class:`~mifacerf.synthetic.Control` list (default: the procedural
    subject's); controls the script names but the subject lacks are ignored.
    """
    if controls is None:
        from ..synthetic.expressions import CONTROLS as controls
    controls = list(controls)
    names = [c.name for c in controls] if control_names is None else list(control_names)
    if seconds <= 0 or fps <= 0:
        raise ValueError("a performance needs a positive length and frame rate")
    n = max(2, int(round(seconds * fps)))
    t = np.arange(n) / fps
    rng = np.random.default_rng(seed)
    idx = {nm: i for i, nm in enumerate(names)}
    base = np.array([c.default for c in controls], np.float64)
    P = np.tile(base, (n, 1))
    events: dict = {"visemes": [], "emotions": [], "blinks": [], "saccades": [], "lead_in_s": LEAD_IN}
    active = t >= LEAD_IN
    fade = _smoothstep((t - LEAD_IN) / 0.25)

    def add(name, values):
        if name in idx:
            P[:, idx[name]] += values

    # ---- speech: visemes with Gaussian dominance, words separated by pauses
    centres, targets, widths = [], [], []
    now = LEAD_IN + 0.15
    while now < seconds - 0.15:
        word, seq = WORDS[rng.integers(len(WORDS))]
        for v in seq:
            dur = rng.uniform(0.07, 0.16)
            amp = rng.uniform(0.75, 1.25)
            centres.append(now + dur / 2)
            targets.append({k: amp * x for k, x in VISEMES[v].items()})
            widths.append(max(0.5 * dur, 0.045))
            events["visemes"].append({"viseme": v, "word": word, "start": round(now, 4), "duration": round(dur, 4),
                                      "amplitude": round(amp, 3)})
            now += dur
        now += rng.uniform(0.08, 0.3)  # pause between words
    if centres:
        c = np.array(centres)
        w = np.array(widths)
        D = np.exp(-0.5 * ((t[:, None] - c[None]) / w[None]) ** 2)          # (n, K) dominance
        rest = 0.08                                                          # the rest shape's dominance
        Wn = D / (D.sum(1, keepdims=True) + rest)
        onset = _smoothstep((t - LEAD_IN) / 0.12)      # the mouth leaves the rest shape smoothly
        for k, tgt in enumerate(targets):
            for name, val in tgt.items():
                add(name, Wn[:, k] * val * onset)

    # ---- emotions coming and going
    start = LEAD_IN + rng.uniform(0.05, 0.2)
    order = list(EMOTIONS)
    rng.shuffle(order)
    k = 0
    while start < seconds - 0.3:
        name = order[k % len(order)]
        attack, hold, release = rng.uniform(0.2, 0.3), rng.uniform(0.15, 0.4), rng.uniform(0.25, 0.4)
        strength = rng.uniform(0.6, 1.0)
        env = strength * _envelope(t, start, attack, hold, release)
        for cname, val in EMOTIONS[name].items():
            add(cname, env * val)
        events["emotions"].append({"emotion": name, "start": round(start, 4), "attack": round(attack, 3),
                                   "hold": round(hold, 3), "release": round(release, 3),
                                   "strength": round(strength, 3)})
        start += attack + hold + release + rng.uniform(0.0, 0.15)
        k += 1

    # ---- head motion (slow sinusoids + a nod), faded in after the lead-in
    for cname, amp, freqs in (("head_yaw", 0.16, (0.35, 0.8)), ("head_pitch", 0.07, (0.5, 1.1)),
                              ("head_roll", 0.05, (0.3, 0.7)), ("jaw_sideways", 0.015, (0.6,))):
        sig = np.zeros(n)
        for f in freqs:
            ph = rng.uniform(0, 2 * np.pi)
            sig += np.sin(2 * np.pi * f * (t - LEAD_IN) + ph) - np.sin(ph)
        add(cname, amp / len(freqs) * sig * fade)
    nod_t = LEAD_IN + rng.uniform(0.4, max(0.5, seconds - 0.6))
    add("head_pitch", -0.06 * _envelope(t, nod_t, 0.15, 0.05, 0.2))
    events["nod"] = round(float(nod_t), 4)

    # ---- blinks (both eyes) and gaze saccades
    bt = LEAD_IN + rng.uniform(0.15, 0.6)
    while bt < seconds - 0.1:
        depth = 1.0 if (rng.random() > 0.2 or not events["blinks"]) else 0.6   # the first blink is a full one
        prof = _blink_profile(t, bt, depth=depth)
        add("blink_L", prof)
        add("blink_R", prof)
        events["blinks"].append({"start": round(bt, 4), "depth": depth})
        bt += rng.uniform(0.8, 2.0)
    gaze = np.zeros((n, 2))
    st = LEAD_IN + rng.uniform(0.1, 0.3)
    prev = np.zeros(2)
    while st < seconds:
        tgt = np.array([rng.uniform(-0.25, 0.25), rng.uniform(-0.12, 0.15)])
        s = _smoothstep((t - st) / 0.04)[:, None]
        gaze += s * (tgt - prev)[None]
        events["saccades"].append({"start": round(st, 4), "gaze_yaw": round(float(tgt[0]), 4),
                                   "gaze_pitch": round(float(tgt[1]), 4)})
        prev = tgt
        st += rng.uniform(0.4, 0.9)
    add("gaze_yaw", gaze[:, 0])
    add("gaze_pitch", gaze[:, 1])

    lo = np.array([c.lo for c in controls])
    hi = np.array([c.hi for c in controls])
    P = np.clip(P, lo, hi)
    P[~active] = base
    return Script(P, float(fps), names, events)


def blend_residual(params: np.ndarray, expressions: np.ndarray, scale: np.ndarray | None = None) -> np.ndarray:
    """Distance (N,) of every parameter vector from the convex hull of ``expressions`` (E, P).

    Each control is divided by ``scale`` (its range) first, so the distance is in units of
    full control ranges. Solved as a non-negative least-squares problem with the sum-to-one
    constraint appended as a heavily weighted row.
    """
    from scipy.optimize import nnls

    X = np.asarray(expressions, np.float64)
    P = np.asarray(params, np.float64)
    s = np.ones(X.shape[1]) if scale is None else np.asarray(scale, np.float64)
    A = np.vstack([(X / s).T, 1e3 * np.ones((1, len(X)))])
    out = np.empty(len(P))
    for i, p in enumerate(P):
        b = np.concatenate([p / s, [1e3]])
        w, _ = nnls(A, b)
        out[i] = np.linalg.norm((X / s).T @ w - p / s)
    return out
