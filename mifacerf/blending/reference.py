"""The straightforward NumPy/SciPy per-vertex evaluation of blend weights (the reference).

For each fiducial vertex in a Python loop, vectorised over frames only:
Horn-align the frames' neighbourhoods (:func:`~mifacerf.geometry.horn1987.horn`), project
onto the vertex's PCA basis, ``scipy.spatial.Delaunay.find_simplex`` + its
``transform`` for the barycentrics (``np.searchsorted`` on the sorted intervals
for ``m = 1``), and the nearest hull facet (brute force over facets) for targets
outside the hull.  It defines the weights the Dr.Jit evaluator
(:mod:`mifacerf.blending.weights`) must reproduce, and is the baseline of the
benchmark.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial import Delaunay

from ..blas import single_threaded_blas
from .delaunay import LocalTriangulation, barycentric_bruteforce, nearest_on_hull
from ..geometry.horn1987 import horn

__all__ = ["vertex_coords", "vertex_weights", "reference_fiducial_weights"]


def vertex_coords(model, f: int, targets) -> np.ndarray:
    """PCA coordinates ``(T, m)`` of fiducial row ``f``'s local deformation in each target ``(T, V, 3)``."""
    targets = np.asarray(targets, dtype=np.float64)
    n = int(model.nbhd.count[model.fiducials[f]])
    idx = model.nbhd.index[model.fiducials[f]]
    P = targets[:, idx[:n], :]
    Q = model.neutral[idx[:n]]
    R, t = horn(P, np.broadcast_to(Q, P.shape))
    A = P @ np.swapaxes(R, -1, -2) + t[:, None, :]
    D = np.broadcast_to(model.spaces[f].mean, (targets.shape[0],) + model.spaces[f].mean.shape).copy()
    D[:, :n] = A
    return model.spaces[f].project(D)[:, : model.triangulations[f].m]


def _qhull(tri: LocalTriangulation):
    """The scipy ``Delaunay`` of the triangulation; rebuilt (and checked) for loaded models."""
    if tri.qhull is None and tri.method.startswith("delaunay"):
        q = Delaunay(tri.points)
        if np.array_equal(q.simplices, tri.simplices):
            tri.qhull = q
    return tri.qhull


def vertex_weights(tri: LocalTriangulation, z, inside_tol: float = 1e-10):
    """Weights of coordinates ``z`` ``(T, m)``: ``(ids (T, m+1) int64, w (T, m+1) float64)``.

    Unused slots (outside the hull the facet has ``m`` vertices) hold weight 0 and repeat the first id.
    """
    z = np.asarray(z, dtype=np.float64)
    Tn, m = z.shape[0], tri.m
    if m == 0:
        return np.repeat(tri.point_ids[:1][None], Tn, axis=0), np.ones((Tn, 1))
    if m == 1:
        order = np.argsort(tri.points[:, 0])
        xs = tri.points[order, 0]
        k = np.clip(np.searchsorted(xs, z[:, 0]) - 1, 0, xs.size - 2)
        # the interval simplices are stored in sorted order: simplex k = (order[k], order[k+1])
        s = k
        b0 = (z[:, 0] - xs[k + 1]) / (xs[k] - xs[k + 1])
        b = np.stack([b0, 1 - b0], axis=1)
        bmin = b.min(axis=1)
    else:
        q = _qhull(tri)
        if q is not None:
            sq = q.find_simplex(z)
            s = np.maximum(sq, 0)
            Tm = q.transform[s, :m, :]
            c = np.einsum("tij,tj->ti", Tm, z - q.transform[s, m, :])
            b = np.concatenate([c, 1 - c.sum(axis=1, keepdims=True)], axis=1)
            # outside the hull, or in a ghost sliver (delaunay rule 4b): the nearest-boundary rule
            bmin = np.where((sq >= 0) & ~tri.ghost[s], b.min(axis=1), -np.inf)
            simplices = q.simplices
        else:
            s, b, bmin = barycentric_bruteforce(tri, z)
            simplices = tri.simplices
    ids = tri.point_ids[(tri.simplices if m == 1 else simplices)[s]]
    w = np.clip(b, 0.0, None)
    out = bmin < -inside_tol
    if np.any(out):
        f, fb, _ = nearest_on_hull(tri, z[out])
        fid = tri.point_ids[tri.facets[f]]
        ids[out] = np.concatenate([fid, fid[:, :1]], axis=1)
        w[out] = np.concatenate([np.clip(fb, 0.0, None), np.zeros((fb.shape[0], 1))], axis=1)
    w /= w.sum(axis=1, keepdims=True)
    return ids, w


def reference_fiducial_weights(model, targets, inside_tol: float = 1e-10):
    """Per-fiducial weights of targets ``(T, V, 3)``: ``(ids (T, F, 4) int32, w (T, F, 4) float64)``.

    A Python loop over fiducial vertices (BLAS single-threaded: the calls are tiny); see the module
    docstring.
    """
    with single_threaded_blas():
        return _reference_fiducial_weights(model, targets, inside_tol)


def _reference_fiducial_weights(model, targets, inside_tol):
    targets = np.asarray(targets, dtype=np.float64)
    Tn, F = targets.shape[0], model.fiducials.size
    ids = np.zeros((Tn, F, 4), dtype=np.int32)
    w = np.zeros((Tn, F, 4), dtype=np.float64)
    for f in range(F):
        tri = model.triangulations[f]
        if tri.m == 0:
            i, ww = vertex_weights(tri, np.zeros((Tn, 0)))
        else:
            i, ww = vertex_weights(tri, vertex_coords(model, f, targets), inside_tol)
        k = i.shape[1]
        ids[:, f, :k] = i
        ids[:, f, k:] = i[:, :1]
        w[:, f, :k] = ww
    return ids, w
