"""Render chunks (paper §6.2–6.3): which reflectance fields a frame needs, with what per-vertex weights.

For a target (template vertices in world), per-vertex expression weights and a render
camera, :func:`plan_frame` computes for every vertex ``v`` and source expression ``s``
with a non-zero weight:

* the local rotation ``R_ts`` (target pose → source pose; Horn on the vertex's
  2-ring neighbourhood, :func:`mifacerf.blending.local_rotations`);
* the render camera's inverse look vector (−optical axis; the paper's choice, the same
  for every vertex, so a capture camera rendering a captured expression samples
  exactly itself), rotated by ``R_ts`` and turned into 1–3 capture-camera weights
  (:class:`.views.ViewSampler`), in two tiers:

  - **primary**: cameras that see ``v`` *or a vertex of a triangle round it* in ``s``
    (:func:`seen_near`) keep their weight, the rest are dropped and the weights
    renormalised. Which pixels of those triangles a camera really sees is decided per
    pixel by the shading kernel's depth test (:meth:`.frame.LitFrame.shade`), so a triangle
    that crosses a silhouette in camera ``c`` is shaded from ``c`` wherever ``c`` sees it,
    not blended with another camera's view of it because one of its corners is hidden.
  - **fallback** (the paper's per-vertex rule): cameras in which ``v`` itself is not
    visible are dropped; if none of them sees ``v``, the visible camera nearest in
    direction is used. The kernel uses it only where no primary chunk passes the depth test.

  In both, if no camera sees ``v`` in ``s``, the pair contributes nothing (the renderer
  renormalises per pixel).

A :class:`RenderChunk` is one (source expression, capture camera) field with its two
per-vertex weights = expression weight × camera weight of each tier. Chunks whose weights
are all zero in both tiers are never created, so their fields are never loaded.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..camera import Camera
from .views import ViewSampler


@dataclass
class RenderChunk:
    """One reflectance field of a frame: source expression ``s``, capture camera ``c``, and the
    per-vertex weights (T,) it is accumulated with (expression weight × camera weight):
    ``weights`` of the primary tier, ``fallback`` of the per-vertex-visibility tier."""

    frame: int
    s: int
    c: int
    weights: np.ndarray
    fallback: np.ndarray


@dataclass
class FramePlan:
    """Everything a frame's render needs besides the fields themselves.

    ``target`` (T, 3) world; ``expression_weights`` (T, S) dense; ``rotations`` {s: (T, 3, 3)}
    for every source used (identity where the weight is 0); ``chunks``; ``unseen`` (T, S) bool:
    (vertex, source) pairs with weight but no camera seeing the vertex.
    """

    frame: int
    target: np.ndarray
    expression_weights: np.ndarray
    rotations: dict
    chunks: list = field(default_factory=list)
    unseen: np.ndarray | None = None

    @property
    def sources(self) -> list[int]:
        return sorted(self.rotations)


def plan_frame(model, target: np.ndarray, expression_weights: np.ndarray, camera: Camera, frame: int = 0,
               neighbourhoods=None, weight_eps: float = 1e-6) -> FramePlan:
    """Plan one frame. ``expression_weights`` (T, S) dense, rows ≥ 0 summing to 1 (validated)."""
    from ..blending import local_rotations
    from ..blending.deformation import align_neighbourhoods
    from ..blending.neighbourhoods import Neighbourhoods

    T, S = model.n_vertices, len(model.expressions)
    target = np.asarray(target, np.float64)
    W = np.asarray(expression_weights, np.float64)
    if target.shape != (T, 3):
        raise ValueError(f"target mesh has shape {target.shape}; the model's template has ({T}, 3)")
    if not np.isfinite(target).all():
        raise ValueError("target mesh has NaN/Inf vertices")
    if W.shape != (T, S):
        raise ValueError(f"expression weights have shape {W.shape}, expected ({T}, {S})")
    if not np.isfinite(W).all() or (W < -1e-9).any():
        raise ValueError("expression weights must be finite and non-negative")
    W = np.where(W > weight_eps, W, 0.0)
    W /= np.maximum(W.sum(1, keepdims=True), 1e-300)
    nb = neighbourhoods if neighbourhoods is not None else model.blend.nbhd
    sampler = ViewSampler.from_cameras(model.cameras)
    cam_dirs = np.stack([-c.forward for c in model.cameras])
    view = np.broadcast_to(-camera.forward, target.shape)
    plan = FramePlan(frame, target, W, {}, [], np.zeros((T, S), bool))
    C = len(model.cameras)
    for s in np.flatnonzero(W.max(0) > 0):
        used = W[:, s] > 0
        R = np.broadcast_to(np.eye(3), (T, 3, 3)).copy()
        if isinstance(nb, Neighbourhoods):   # the rotations of the vertices it weighs only (~1/5 of them in a drive)
            R[used] = align_neighbourhoods(target, model.vertices[s], nb, rows=np.flatnonzero(used))[1]
        else:
            R[used] = local_rotations(target, model.vertices[s], nb)[used]
        plan.rotations[int(s)] = R
        rv = np.einsum("tij,tj->ti", R, view)[used]  # the novel view in the source's local pose
        idx, w = sampler.weights(rv)
        raw = np.zeros((used.sum(), C))
        np.add.at(raw, (np.arange(len(idx))[:, None].repeat(3, 1), idx), w)
        vis = model.visible[s][:, used].T  # (n_used, C)
        near = model.visible_near[s][:, used].T
        fallback, lost = _camera_weights(raw, vis, vis, rv, cam_dirs)
        primary, _ = _camera_weights(raw, near, vis, rv, cam_dirs)
        plan.unseen[np.flatnonzero(used)[lost], s] = True
        for c in range(C):
            a, f = np.zeros(T), np.zeros(T)
            a[used] = W[used, s] * primary[:, c]
            f[used] = W[used, s] * fallback[:, c]
            if max(a.max(), f.max()) > weight_eps and model.has_field(int(s), c):
                plan.chunks.append(RenderChunk(frame, int(s), c, a, f))
    return plan


def seen_near(visible: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """(C, T) bool: vertex ``v`` is seen *near* in camera ``c`` when some triangle round it has a
    vertex visible in ``c``. ``visible`` (C, T) bool, per-vertex visibility; ``triangles`` (F, 3)."""
    visible = np.asarray(visible, bool)
    tri = np.asarray(triangles, np.int64)
    any_seen = visible[:, tri].any(axis=2).astype(np.int32)  # (C, F)
    count = np.zeros(visible.shape, np.int32)
    for k in range(3):
        np.add.at(count.T, tri[:, k], any_seen.T)
    return visible | (count > 0)


def _camera_weights(raw, keep, visible, view, cam_dirs):
    """Per-vertex camera weights (N, C): the interpolation weights ``raw`` (N, C) restricted to
    cameras with ``keep`` (N, C) and renormalised; a vertex left with none gets weight 1 on the
    ``visible`` camera nearest in direction to ``view`` (N, 3) (``cam_dirs`` (C, 3) inverse look
    vectors), or none when no camera sees it. Returns (weights, lost (N,) bool: no camera sees it)."""
    cw = raw * keep
    tot = cw.sum(1)
    empty = tot <= 1e-12
    lost = np.zeros(len(cw), bool)
    if empty.any():
        score = np.where(visible[empty], view[empty] @ cam_dirs.T, -np.inf)
        best = score.argmax(1)
        ok = np.isfinite(score.max(1))
        cw[np.flatnonzero(empty)[ok], best[ok]] = 1.0
        lost[np.flatnonzero(empty)[~ok]] = True
        tot = cw.sum(1)
    return cw / np.maximum(tot, 1e-300)[:, None], lost
