"""Eyes, lips and eyelids from a few hand-marked keyframes (paper §6.4, with §4.2's tools).

"The irises are again marked, although now we have the option of marking only keyframes and
interpolating between them. The eye centers are placed relative to the head pose."
:func:`eye_tracks`: at every iris keyframe the iris outlines (≥ 2 views) give the 3-D iris
centre (ellipse centres triangulated, :func:`mifacerf.registration.eyes_teeth.iris_centre`); the
eyeball centre is the reference's centre carried by the frame's head pose; the gaze is the unit
vector between them, expressed in the head frame. Gazes are interpolated between keyframes
(spherical linear), held before the first and after the last, and turned back into eyeball
transforms (rest → world: yaw then pitch about the eyeball centre, then the head pose).

"The lips are also placed as in Section 4.2. Again, we need rotoscope only a few keyframes where
the shapes of the lips are changing most dramatically. The in-between frames are computed by
applying the motion of the dots nearest the lips." :func:`margin_tracks`: at a keyframe, each
rotoscoped margin (lips, and the eyelids "warped into place in the same way") is relaxed onto its
curves (:func:`mifacerf.registration.contours.relax_margin`) from the dots' estimate; in any other
frame, the margins of the keyframes before and after are carried to that frame by the motion of
the dots nearest the margin (a moving-least-squares affine map from the keyframe's dot positions
to the frame's) and cross-faded by time.
"""
from __future__ import annotations

import numpy as np

from ..camera import Camera
from ..geometry.rigid import apply as apply_T
from ..registration import eyes_teeth as ET
from ..registration.contours import relax_margin
from ..geometry.schaefer2006 import mls_affine

LIP_MARGINS = ("lip_upper", "lip_lower")
LID_MARGINS = ("lid_upper_L", "lid_lower_L", "lid_upper_R", "lid_lower_R")


def _bracket(keys: list[int], f: int) -> tuple[int | None, int | None, float]:
    """Keyframes before / after ``f`` and the blend weight of the later one."""
    before = [k for k in keys if k <= f]
    after = [k for k in keys if k >= f]
    a = before[-1] if before else None
    b = after[0] if after else None
    if a is None:
        return b, b, 0.0
    if b is None or b == a:
        return a, a, 0.0
    return a, b, (f - a) / (b - a)


def near_dots(X_ref_dots: np.ndarray, points: np.ndarray, k: int) -> np.ndarray:
    """Indices of the ``k`` dots nearest to any of ``points`` (by distance to the set)."""
    d = np.linalg.norm(X_ref_dots[:, None] - points[None], axis=-1).min(1)
    return np.argsort(d)[:k]


def margin_tracks(V: np.ndarray, X: np.ndarray, margins: dict, keyed: dict, rotoscope: dict,
                  cams: dict, X_ref: np.ndarray, V_ref: np.ndarray | None = None, n_near: int = 12) -> tuple[dict, dict]:
    """Margin positions per frame {margin: (N, n, 3)} and a report.

    ``V`` (N, T, 3): the per-frame template from the dots (margins only morphed); ``X`` (N, D, 3)
    the dots; ``margins`` {name: template ids}; ``keyed`` {name: [keyframes]}; ``rotoscope``
    {frame: Rotoscope}; ``cams`` {name: Camera}; ``X_ref`` (D, 3) the dots and ``V_ref`` (T, 3) the
    template at rest (to choose the dots nearest each margin).
    """
    N = len(V)
    out, report = {}, {}
    for name, ids in margins.items():
        ids = np.asarray(ids, np.int64)
        shapes = {}
        for f in keyed.get(name, []):
            rot = rotoscope.get(f)
            views = {} if rot is None else {c: p for c, p in rot.curves.get(name, {}).items() if c in cams}
            if len(views) >= 2 and 0 <= f < N:
                shapes[f] = relax_margin(V[f, ids], views, cams)
        keys = sorted(shapes)
        report[name] = {"keyframes": keys}
        if not keys:
            out[name] = V[:, ids].copy()
            report[name]["source"] = "no keyframe: moved with the dots only"
            continue
        near = near_dots(X_ref, (V[keys[0]] if V_ref is None else V_ref)[ids], n_near)
        M = np.empty((N, len(ids), 3))
        for f in range(N):
            a, b, w = _bracket(keys, f)
            Ma = shapes[a] if a == f else mls_affine(X[a, near], X[f, near], shapes[a], k=None)
            if w == 0.0 or b == a:
                M[f] = Ma
                continue
            Mb = shapes[b] if b == f else mls_affine(X[b, near], X[f, near], shapes[b], k=None)
            M[f] = (1 - w) * Ma + w * Mb
        out[name] = M
        report[name]["source"] = f"{len(keys)} rotoscoped keyframe(s), in-betweens moved with the {len(near)} nearest dots"
    return out, report


def _rot_from_gaze(g: np.ndarray) -> np.ndarray:
    """Rotation (3, 3) taking the head frame's +Z to ``g`` by a yaw about +Y then a pitch about +X."""
    g = g / np.linalg.norm(g)
    yaw = np.arctan2(g[0], g[2])
    pitch = np.arcsin(np.clip(g[1], -1, 1))
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(-pitch), np.sin(-pitch)
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rx = np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])
    return Ry @ Rx


def _slerp(a: np.ndarray, b: np.ndarray, w: float) -> np.ndarray:
    a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
    om = np.arccos(np.clip(a @ b, -1, 1))
    if om < 1e-8:
        return a
    return (np.sin((1 - w) * om) * a + np.sin(w * om) * b) / np.sin(om)


def eye_tracks(head: np.ndarray, centres_head: dict, keyed: list[int], rotoscope: dict,
               cams: list[Camera]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Per-frame eyeball transforms (N, 2, 4, 4) (left, right; rest → world), gazes (N, 2, 3) in world,
    and a report. ``centres_head`` {"L"/"R": (3,)} eyeball centres in the neutral head frame."""
    N = len(head)
    T = np.tile(np.eye(4), (N, 2, 1, 1))
    gaze = np.full((N, 2, 3), np.nan)
    report = {}
    for i, side in enumerate(("L", "R")):
        c_head = np.asarray(centres_head.get(side, np.full(3, np.nan)), np.float64)
        if not np.isfinite(c_head).all():
            report[side] = {"source": "no eyeball centre in the template / model"}
            continue
        keys = {}
        for f in keyed:
            rot = rotoscope.get(f)
            views = {} if rot is None else {c: p for c, p in rot.curves.get(f"iris_{side}", {}).items()
                                            if c in {cam.name for cam in cams}}
            if len(views) < 2 or not 0 <= f < N:
                continue
            iris = ET.iris_centre(cams, views)
            if iris is None:
                continue
            centre = apply_T(head[f], c_head[None])[0]
            g_world = iris - centre
            keys[f] = head[f, :3, :3].T @ (g_world / np.linalg.norm(g_world))
        kf = sorted(keys)
        report[side] = {"keyframes": kf}
        for f in range(N):
            if kf:
                a, b, w = _bracket(kf, f)
                g = keys[a] if a == b else _slerp(keys[a], keys[b], w)
            else:
                g = np.array([0.0, 0.0, 1.0])
            R = _rot_from_gaze(g)
            local = np.eye(4)
            local[:3, :3] = R
            local[:3, 3] = c_head - R @ c_head
            T[f, i] = head[f] @ local
            gaze[f, i] = head[f, :3, :3] @ g
        report[side]["source"] = (f"{len(kf)} iris keyframe(s), interpolated, centre relative to the head pose"
                                  if kf else "no iris keyframe: looking straight ahead (predicted)")
    return T, gaze, report
