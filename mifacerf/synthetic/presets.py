"""Captured-expression presets of the procedural subject (Hawkins et al. 2004, §2.2).

One ordered list of 60 expressions; a preset of size ``n`` is its first ``n`` entries:

* ``tiny`` (6): neutral, smile, viseme /a/ (open mouth), head turned left, eyes closed, surprise;
* ``draft`` (24): the tiny six, then anger, visemes /f,v/ /p,b,m/ /oo/ /w,r/ /t,d,s,z/ /uh/, teeth
  bared, eyes wide open, disgust, sadness, fear, head turned right / up / down, look left / up,
  mouth wide open;
* ``paper`` (60): the draft 24 plus more emotions, visemes, mouth shapes, eye positions, head poses
  and coverage expressions.

Categories: ``neutral``, ``emotion``, ``viseme``, ``mouth``, ``head_pose``, ``eyes``, ``coverage``.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .expressions import CONTROL_INDEX, default_params


class Expression(NamedTuple):
    name: str
    category: str
    params: np.ndarray


def _both(prefix, v):
    return {f"{prefix}_L": v, f"{prefix}_R": v}


_LIST = [
    # ---- tiny (first 6) -------------------------------------------------------------------
    ("neutral", "neutral", {}),
    ("smile", "emotion", {**_both("smile", 1.0), **_both("cheek_raise", 0.6), "upper_lip_raise": 0.1}),
    ("viseme_aa", "viseme", {"jaw_open": 0.27, "lower_lip_down": 0.35, "upper_lip_raise": 0.2}),
    ("head_turn_left", "head_pose", {"head_yaw": 0.45}),
    ("eyes_closed", "coverage", {**_both("blink", 1.0)}),
    ("surprise", "emotion", {**_both("brow_raise", 1.0), "eyes_wide": 1.0, "jaw_open": 0.2, "funnel": 0.25}),
    # ---- draft (to 24) --------------------------------------------------------------------
    ("anger", "emotion", {"frown": 1.0, **_both("brow_lower", 0.8), "lips_press": 0.6, "nose_wrinkle": 0.25}),
    ("viseme_fv", "viseme", {"lower_lip_tuck": 1.0, "upper_lip_raise": 0.25, "jaw_open": 0.03}),
    ("viseme_pbm", "viseme", {"lips_press": 1.0}),
    ("viseme_oo", "viseme", {"pucker": 1.0, "funnel": 0.4, "jaw_open": 0.08}),
    ("viseme_wr", "viseme", {"pucker": 0.7, "funnel": 0.3, "jaw_open": 0.05}),
    ("viseme_tdsz", "viseme", {"jaw_open": 0.05, "mouth_stretch": 0.4, "upper_lip_raise": 0.3,
                               "lower_lip_down": 0.35}),
    ("viseme_uh", "viseme", {"jaw_open": 0.17, "lower_lip_down": 0.15}),
    ("teeth_bared", "coverage", {"upper_lip_raise": 1.0, "lower_lip_down": 1.0, "mouth_stretch": 0.5,
                                 **_both("smile", 0.3), "jaw_open": 0.03}),
    ("eyes_wide_open", "coverage", {"eyes_wide": 1.0, **_both("brow_raise", 0.5)}),
    ("disgust", "emotion", {"nose_wrinkle": 1.0, "upper_lip_raise": 0.7, "lip_corner_down": 0.5,
                            **_both("brow_lower", 0.5), **_both("cheek_raise", 0.4)}),
    ("sadness", "emotion", {"lip_corner_down": 1.0, **_both("brow_raise", 0.3), "frown": 0.5,
                            "lips_press": 0.2, "gaze_pitch": -0.15}),
    ("fear", "emotion", {**_both("brow_raise", 0.8), "frown": 0.4, "eyes_wide": 1.0, "mouth_stretch": 0.8,
                         "jaw_open": 0.1}),
    ("head_turn_right", "head_pose", {"head_yaw": -0.45}),
    ("head_up", "head_pose", {"head_pitch": 0.28}),
    ("head_down", "head_pose", {"head_pitch": -0.28}),
    ("look_left", "eyes", {"gaze_yaw": 0.4}),
    ("look_up", "eyes", {"gaze_pitch": 0.3}),
    ("mouth_open_wide", "mouth", {"jaw_open": 0.36, "lower_lip_down": 0.3, "upper_lip_raise": 0.2}),
    # ---- paper (to 60) --------------------------------------------------------------------
    ("smile_open", "emotion", {**_both("smile", 1.0), **_both("cheek_raise", 0.8), "jaw_open": 0.12,
                               "upper_lip_raise": 0.4, "lower_lip_down": 0.3}),
    ("anger_teeth", "emotion", {"frown": 1.0, **_both("brow_lower", 1.0), "upper_lip_raise": 0.8,
                                "lower_lip_down": 0.6, "nose_wrinkle": 0.6}),
    ("contempt", "emotion", {"smile_L": 0.6, "cheek_raise_L": 0.3, "lips_press": 0.3}),
    ("viseme_ee", "viseme", {"mouth_stretch": 0.7, **_both("smile", 0.3), "jaw_open": 0.06}),
    ("viseme_ch_sh", "viseme", {"funnel": 1.0, "pucker": 0.3, "jaw_open": 0.05}),
    ("viseme_th", "viseme", {"jaw_open": 0.08, "lower_lip_down": 0.2}),
    ("viseme_kg", "viseme", {"jaw_open": 0.15, "mouth_stretch": 0.2}),
    ("viseme_l", "viseme", {"jaw_open": 0.14, "upper_lip_raise": 0.1}),
    ("viseme_ao", "viseme", {"jaw_open": 0.22, "pucker": 0.4, "funnel": 0.4}),
    ("mouth_left", "mouth", {"jaw_sideways": 0.08, "smile_L": 0.3}),
    ("mouth_right", "mouth", {"jaw_sideways": -0.08, "smile_R": 0.3}),
    ("lips_rolled_in", "mouth", {"lips_roll_in": 1.0}),
    ("pucker", "mouth", {"pucker": 1.0}),
    ("funnel", "mouth", {"funnel": 1.0, "jaw_open": 0.1}),
    ("lip_corners_down", "mouth", {"lip_corner_down": 1.0}),
    ("mouth_stretch", "mouth", {"mouth_stretch": 1.0}),
    ("lower_lip_down", "mouth", {"lower_lip_down": 1.0}),
    ("upper_lip_raise", "mouth", {"upper_lip_raise": 1.0}),
    ("jaw_half_open", "mouth", {"jaw_open": 0.18}),
    ("smile_left", "emotion", {"smile_L": 1.0, "cheek_raise_L": 0.6}),
    ("smile_right", "emotion", {"smile_R": 1.0, "cheek_raise_R": 0.6}),
    ("brows_up", "emotion", {**_both("brow_raise", 1.0)}),
    ("brows_down", "emotion", {**_both("brow_lower", 1.0)}),
    ("squint", "eyes", {**_both("cheek_raise", 1.0)}),
    ("wink_left", "eyes", {"blink_L": 1.0, "cheek_raise_L": 0.4}),
    ("wink_right", "eyes", {"blink_R": 1.0, "cheek_raise_R": 0.4}),
    ("look_right", "eyes", {"gaze_yaw": -0.4}),
    ("look_down", "eyes", {"gaze_pitch": -0.3}),
    ("look_up_left", "eyes", {"gaze_yaw": 0.3, "gaze_pitch": 0.25}),
    ("head_tilt_left", "head_pose", {"head_roll": 0.25}),
    ("head_tilt_right", "head_pose", {"head_roll": -0.25}),
    ("head_left_up", "head_pose", {"head_yaw": 0.35, "head_pitch": 0.2}),
    ("head_right_down", "head_pose", {"head_yaw": -0.35, "head_pitch": -0.2}),
    ("nose_wrinkle", "mouth", {"nose_wrinkle": 1.0}),
    ("eyes_closed_tight", "coverage", {**_both("blink", 1.0), **_both("cheek_raise", 0.8), "frown": 0.3}),
    ("teeth_bared_open", "coverage", {"upper_lip_raise": 1.0, "lower_lip_down": 1.0, "jaw_open": 0.15}),
]

PRESET_SIZES = {"tiny": 6, "draft": 24, "paper": 60}
CATEGORIES = ("neutral", "emotion", "viseme", "mouth", "head_pose", "eyes", "coverage")


def params_from(named: dict) -> np.ndarray:
    p = default_params()
    for k, v in named.items():
        if k not in CONTROL_INDEX:
            raise KeyError(f"unknown control {k!r}")
        p[CONTROL_INDEX[k]] = v
    return p


def all_expressions() -> list[Expression]:
    return [Expression(n, c, params_from(d)) for (n, c, d) in _LIST]


def presets(n) -> list[Expression]:
    """The first ``n`` expressions (``n`` in 6, 24, 60 or 'tiny' / 'draft' / 'paper')."""
    if isinstance(n, str):
        if n not in PRESET_SIZES:
            raise ValueError(f"unknown preset {n!r}; use one of {sorted(PRESET_SIZES)}")
        n = PRESET_SIZES[n]
    n = int(n)
    if n not in PRESET_SIZES.values():
        raise ValueError(f"preset size must be one of {sorted(PRESET_SIZES.values())}, got {n}")
    return all_expressions()[:n]
