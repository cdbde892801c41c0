"""Blends of captured expressions that turn the head: the rigid head motion blended as a motion.

A captured expression's registered geometry is its head pose (``head_pose`` (4, 4), neutral → expression,
from the registration) applied to the face in the head's frame. Blending the vertices linearly blends the
head's rotation along chords: 0.4 of a 30° turn lands a point 10 cm from the turn's axis ~3 mm inside the
arc the subject's head follows (the truth of a blend of parameter vectors turns the head by the blended
angle). :func:`blend_geometry` instead blends each expression's face in its head frame linearly and the
head poses as rigid motions, :func:`blend_motions` — the exponential of the weighted mean of the motions'
logarithms (a twist: for turns about one axis through one pivot, exactly the turn by the blended angle).
One expression with weight 1 gives its registered vertices (to rounding).
"""
from __future__ import annotations

import numpy as np


#: logm of the rigid motions blended so far, by their bytes: the captured head poses are the same every
#: frame (and a frame blends them twice, for the skin and for the parts), their logarithm is not
_LOGS: dict[bytes, np.ndarray] = {}


def _log(T: np.ndarray) -> np.ndarray:
    from scipy.linalg import logm

    key = T.tobytes()
    L = _LOGS.get(key)
    if L is None:
        if len(_LOGS) >= 4096:
            _LOGS.clear()
        L = _LOGS[key] = np.real(logm(T))
    return L


def blend_motions(Ts, w) -> np.ndarray:
    """(4, 4) weighted blend of rigid motions ``Ts`` (n, 4, 4) with weights ``w`` (n,) summing to 1:
    ``expm(Σ w_i logm(T_i))`` (the log-Euclidean mean on SE(3))."""
    from scipy.linalg import expm

    Ts = np.asarray(Ts, np.float64)
    w = np.asarray(w, np.float64)
    if len(Ts) == 1:
        return Ts[0].copy()
    L = sum(wi * _log(T) for wi, T in zip(w, Ts))
    out = np.real(expm(L))
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def _apply(T, P):
    return P @ T[:3, :3].T + T[:3, 3]


def _inverse(T):
    out = np.eye(4)
    out[:3, :3] = T[:3, :3].T
    out[:3, 3] = -T[:3, :3].T @ T[:3, 3]
    return out


def blend_geometry(vertices, head_pose, weights: dict[int, float]) -> tuple[np.ndarray, np.ndarray]:
    """(the blended (T, 3) vertices, the blended (4, 4) head pose) of expressions ``weights`` {index:
    weight} (weights normalised to sum to 1) of ``vertices`` (S, T, 3) with head poses ``head_pose``
    (S, 4, 4): each expression's vertices taken into its head frame, blended linearly there, and carried
    out by the blended head pose (:func:`blend_motions`)."""
    idx = list(weights)
    if len(idx) == 1:                              # a captured expression: its registered vertices as they are
        return np.array(vertices[idx[0]], np.float64), np.array(head_pose[idx[0]], np.float64)
    w = np.array([weights[s] for s in idx], np.float64)
    w = w / w.sum()
    H = np.asarray(head_pose, np.float64)[idx]
    local = sum(wi * _apply(_inverse(Hi), np.asarray(vertices[s], np.float64)) for wi, Hi, s in zip(w, H, idx))
    Hb = blend_motions(H, w)
    return _apply(Hb, local), Hb


def blend_parts(model, weights: dict[str, float], head: np.ndarray | None = None) -> dict:
    """Eye and teeth transforms {part: 4x4 rest→world} of a blend of captured expressions ``weights``
    {name: weight}: each expression's part transform taken into its head frame, blended there
    (:func:`mifacerf.rendering.parts.blend_transforms`), and carried out by the blended head pose, so the
    eyes and teeth move with the blended skin (:func:`blend_geometry`). ``head``: that blended head pose
    when the caller has it (:func:`blend_geometry`'s second result for the same weights), so a frame
    blends the motions once."""
    from .parts import PARTS, blend_transforms, part_transforms, target_parts_from_weights

    if len(weights) == 1:                          # a captured expression: its registered parts as they are
        return target_parts_from_weights(model, weights)
    idx = [model.expression_index(n) for n in weights]
    w = np.array(list(weights.values()), np.float64)
    w = w / w.sum()
    H = np.asarray(model.head_pose, np.float64)[idx]
    Hb = blend_motions(H, w) if head is None else np.asarray(head, np.float64)
    per = [part_transforms(model.template, model.eye_centres[s], model.teeth[s], model.head_pose[s]) for s in idx]
    out = {}
    for p in PARTS:
        have = [(_inverse(Hi) @ T[p], wi) for T, Hi, wi in zip(per, H, w) if p in T]
        if have:
            ws = np.array([h[1] for h in have])
            out[p] = Hb @ blend_transforms(np.stack([h[0] for h in have]), ws / ws.sum())
    return out
