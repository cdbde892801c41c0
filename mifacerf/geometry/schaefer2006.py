"""Moving-least-squares affine deformation in 3-D (Schaefer, McPhail & Warren 2006).

S. Schaefer, T. McPhail, J. Warren, "Image deformation using moving least squares", SIGGRAPH 2006,
carried to 3-D: each point gets the affine map that best carries nearby anchors (weights
``1 / (ε + d)^(2α)``) onto their new positions, regularised towards the best rigid map
(Horn 1987, :mod:`.horn1987`) of the same anchors, so nearly coplanar anchors stay well-posed.
Every rigid motion is exact; a global affine map is exact up to the small regularisation.
Points are (N, 3) rows in metres (any consistent unit); results are float64.

Registration places the template's extra vertices (nostrils, lips, eyelids, ears) relative to the
registered fiducials with :func:`mls_affine`, and its snap predicts start positions with
:func:`local_affine`; tracking predicts lost dots and carries shapes between frames with it.
"""
from __future__ import annotations

import numpy as np

from .horn1987 import horn


def mls_affine(src_anchors, dst_anchors, points, alpha: float = 1.0, eps: float = 0.003, k: int | None = 24,
               reg: float = 1e-3, anchor_weights=None) -> np.ndarray:
    """Moving-least-squares affine deformation of ``points`` (M, 3).

    ``src_anchors`` / ``dst_anchors`` (K, 3) corresponding anchors (rows with NaN are ignored);
    each point uses its ``k`` nearest anchors (all when None) with weights
    ``1 / (eps + d)^(2 alpha)`` (times ``anchor_weights`` when given). ``reg`` is the
    relative weight of the pull towards the weighted rigid (Horn) map.
    """
    S = np.asarray(src_anchors, np.float64)
    D = np.asarray(dst_anchors, np.float64)
    P = np.asarray(points, np.float64).reshape(-1, 3)
    good = np.isfinite(S).all(1) & np.isfinite(D).all(1)
    aw = np.ones(len(S)) if anchor_weights is None else np.asarray(anchor_weights, np.float64)
    good &= aw > 0
    S, D, aw = S[good], D[good], aw[good]
    if len(S) < 3:
        raise ValueError("mls_affine needs at least three anchors")
    kk = len(S) if k is None else min(k, len(S))
    from scipy.spatial import cKDTree

    dist, idx = cKDTree(S).query(P, kk)
    if kk == 1:
        dist, idx = dist[:, None], idx[:, None]
    w = aw[idx] / (eps + dist) ** (2 * alpha)                 # (M, k)
    Ps, Qs = S[idx], D[idx]                                      # (M, k, 3)
    wsum = w.sum(1, keepdims=True)
    ps = np.einsum("mk,mki->mi", w, Ps) / wsum
    qs = np.einsum("mk,mki->mi", w, Qs) / wsum
    Ph, Qh = Ps - ps[:, None], Qs - qs[:, None]
    R, _ = horn(Ps, Qs, w)                                       # (M, 3, 3) weighted rigid fit
    PtP = np.einsum("mk,mki,mkj->mij", w, Ph, Ph)
    QtP = np.einsum("mk,mki,mkj->mij", w, Qh, Ph)
    lam = reg * np.trace(PtP, axis1=1, axis2=2)[:, None, None] + 1e-18
    A = np.linalg.solve((PtP + lam * np.eye(3)).transpose(0, 2, 1), (QtP + lam * R).transpose(0, 2, 1))
    A = A.transpose(0, 2, 1)
    return qs + np.einsum("mij,mj->mi", A, P - ps)


def local_affine(src: np.ndarray, dst: np.ndarray, w: np.ndarray, q: np.ndarray, reg: float = 0.05) -> np.ndarray:
    """Batched weighted affine maps (regularised towards the weighted rigid map) applied to queries.

    ``src``, ``dst`` (M, K, 3) anchors per query (padding rows with weight 0), ``w`` (M, K),
    ``q`` (M, 3). Queries with no weight stay where they are; with one or two anchors the map is
    their mean translation.
    """
    w = np.asarray(w, np.float64)
    wsum = w.sum(1)
    out = np.asarray(q, np.float64).copy()
    ok = wsum > 0
    if not ok.any():
        return out
    S, D, W, Q = src[ok], dst[ok], w[ok], q[ok]
    ws = W.sum(1, keepdims=True)
    ps = np.einsum("mk,mki->mi", W, S) / ws
    qs = np.einsum("mk,mki->mi", W, D) / ws
    n = (W > 0).sum(1)
    res = Q - ps + qs                                            # translation only
    many = n >= 3
    if many.any():
        Sm, Dm, Wm = S[many], D[many], W[many]
        Ph, Qh = Sm - ps[many, None], Dm - qs[many, None]
        R, _ = horn(Sm, Dm, Wm)
        PtP = np.einsum("mk,mki,mkj->mij", Wm, Ph, Ph)
        QtP = np.einsum("mk,mki,mkj->mij", Wm, Qh, Ph)
        lam = reg * np.trace(PtP, axis1=1, axis2=2)[:, None, None] + 1e-18
        A = np.linalg.solve((PtP + lam * np.eye(3)).transpose(0, 2, 1), (QtP + lam * R).transpose(0, 2, 1))
        A = A.transpose(0, 2, 1)
        res[many] = qs[many] + np.einsum("mij,mj->mi", A, Q[many] - ps[many])
    out[ok] = res
    return out
