"""Local deformation (paper §5) and local rotations ``R_ts`` (paper §6.1).

For a vertex ``v`` with neighbourhood ``V`` and an expression ``S``, the *local
deformation vector* is the neighbourhood's positions after the rigid transform
(Horn 1987) that best maps ``P_S(V)`` onto the neutral's ``P_0(V)``:
``D_S(v) = R_S P_S(V) + t_S``, an ``(|V|, 3)`` array in the neutral's frame
(flattened to ``3|V|`` for PCA).  Rigid motions of the whole expression leave
it unchanged.
"""
from __future__ import annotations

import numpy as np

from ..geometry.horn1987 import horn
from .neighbourhoods import Neighbourhoods

__all__ = ["align_neighbourhoods", "local_rotations", "region_deformations"]


def _as_points(x, name, V=None):
    x = np.asarray(x, dtype=np.float64)
    if x.ndim < 2 or x.shape[-1] != 3 or (V is not None and x.shape[-2] != V):
        want = "(..., V, 3)" if V is None else f"(..., {V}, 3)"
        raise ValueError(f"{name} must have shape {want}; got {x.shape}")
    return x


def align_neighbourhoods(points, reference, nbhd: Neighbourhoods, rows=None):
    """Local deformation vectors of ``points`` against ``reference``.

    Parameters
    ----------
    points : array_like, shape ``(..., V, 3)``
        One or more meshes (world metres).
    reference : array_like, shape ``(V, 3)``
        The mesh every neighbourhood is aligned onto (the neutral).
    nbhd : Neighbourhoods
        Neighbourhoods of all ``V`` vertices.
    rows : array_like of int, shape ``(F,)``, optional
        Only these vertices' neighbourhoods (default all).

    Returns
    -------
    aligned : ndarray, shape ``(..., F, K, 3)``
        ``R P(V) + t`` for each neighbourhood (padding entries hold the aligned centre vertex).
    R : ndarray, shape ``(..., F, 3, 3)``
        The rotations (``points``' local pose into ``reference``'s).
    """
    ref = _as_points(reference, "reference")
    V = ref.shape[-2]
    pts = _as_points(points, "points", V)
    if nbhd.n_vertices != V:
        raise ValueError(f"neighbourhoods are for {nbhd.n_vertices} vertices, meshes have {V}")
    nb = nbhd if rows is None else nbhd.subset(rows)
    idx, mask = nb.index, nb.mask
    P = pts[..., idx, :]                      # (..., F, K, 3)
    Q = ref[idx]                              # (F, K, 3)
    Q = np.broadcast_to(Q, P.shape)
    R, t = horn(P, Q, mask.astype(np.float64))
    aligned = np.einsum("...ab,...kb->...ka", R, P) + t[..., None, :]
    return aligned, R


def local_rotations(target, source, neighbourhoods) -> np.ndarray:
    """Per-vertex rotations ``R_ts`` (paper §6.1).

    Parameters
    ----------
    target : array_like, shape ``(..., V, 3)``
        The novel expression ``t`` (world metres).
    source : array_like, shape ``(..., V, 3)`` (broadcastable with ``target``)
        The source expression ``s`` that is sampled.
    neighbourhoods : Neighbourhoods or sequence of index arrays
        The neighbourhood of each vertex (see :func:`~mifacerf.blending.neighbourhoods`).

    Returns
    -------
    R : ndarray, shape ``(..., V, 3, 3)``
        ``R[i]`` rotates the target's local pose at vertex ``i`` into the source's: the rotation of the
        Horn (1987) rigid transform that best maps ``target[V_i]`` onto ``source[V_i]``.  A direction
        ``d`` expressed relative to the target's local surface becomes ``R @ d`` relative to the
        source's (rendering rotates the view and light directions by it).
    """
    if not isinstance(neighbourhoods, Neighbourhoods):
        neighbourhoods = Neighbourhoods.from_lists(neighbourhoods)
    tgt = _as_points(target, "target")
    src = _as_points(source, "source")
    V = neighbourhoods.n_vertices
    if tgt.shape[-2] != V or src.shape[-2] != V:
        raise ValueError(f"target {tgt.shape} / source {src.shape} must have {V} vertices")
    idx, mask = neighbourhoods.index, neighbourhoods.mask
    P = tgt[..., idx, :]
    Q = src[..., idx, :]
    P, Q = np.broadcast_arrays(P, Q)
    R, _ = horn(P, Q, mask.astype(np.float64))
    return R


def region_deformations(meshes, neutral, vertex_ids) -> np.ndarray:
    """Deformation vectors of one region (paper §5.1).

    Parameters
    ----------
    meshes : array_like, shape ``(n, V, 3)``
    neutral : array_like, shape ``(V, 3)``
    vertex_ids : array_like of int, shape ``(R,)``

    Returns
    -------
    ndarray, shape ``(n, R, 3)``: each mesh's region rigidly aligned (Horn) onto the neutral's region.
    """
    meshes = _as_points(meshes, "meshes")
    neutral = _as_points(neutral, "neutral", meshes.shape[-2])
    ids = np.asarray(vertex_ids, dtype=np.int64)
    if ids.ndim != 1 or ids.size == 0 or ids.min() < 0 or ids.max() >= neutral.shape[0]:
        raise ValueError(f"region vertex ids must be a non-empty 1-D array in [0, {neutral.shape[0]})")
    P = meshes[..., ids, :]
    Q = np.broadcast_to(neutral[ids], P.shape)
    R, t = horn(P, Q)
    return np.einsum("...ab,...kb->...ka", R, P) + t[..., None, :]
