"""The expressions of a capture session (paper §2.2): emotions, visemes, mouth shapes, head
poses, eye positions and coverage of seldom-seen areas, 60 in all as in the paper."""
from __future__ import annotations

from ..formats.capture import ExpressionEntry

#: (name, category) in capture order; the neutral face comes first.
PAPER_SESSION: list[tuple[str, str]] = (
    [("neutral", "neutral")]
    + [(n, "emotion") for n in ("smile", "big_smile", "frown", "surprise", "disgust", "anger", "fear", "sadness",
                                "contempt", "smirk_left", "smirk_right", "squint")]
    + [(n, "viseme") for n in ("f_v", "w_r", "p_b_m", "t_d_s_z", "uh", "oo", "ah", "ee", "th", "k_g", "ch_sh",
                               "l")]
    + [(n, "mouth") for n in ("jaw_open", "jaw_left", "jaw_right", "lips_pursed", "lips_wide", "lips_funnel",
                              "cheeks_puffed", "lip_bite", "tongue_out", "mouth_left", "mouth_right",
                              "lower_lip_down")]
    + [(n, "head_pose") for n in ("head_left", "head_right", "head_up", "head_down", "head_tilt_left",
                                  "head_tilt_right")]
    + [(n, "eyes") for n in ("look_left", "look_right", "look_up", "look_down", "eyes_closed", "eyes_wide",
                             "wink_left", "wink_right")]
    + [(n, "coverage") for n in ("teeth_bared", "teeth_clenched", "mouth_wide_open", "eyelids_closed_tight",
                                 "brows_raised", "brows_lowered", "nostrils_flared", "chin_raised", "neck_tense")]
)


def session_expressions(n: int | None = None) -> list[ExpressionEntry]:
    """The first ``n`` expressions of :data:`PAPER_SESSION` (all 60 by default)."""
    items = PAPER_SESSION if n is None else PAPER_SESSION[:n]
    if n is not None and not 1 <= n <= len(PAPER_SESSION):
        raise ValueError(f"between 1 and {len(PAPER_SESSION)} expressions, got {n}")
    return [ExpressionEntry(name, cat) for name, cat in items]
