"""Multi-view triangulation of 3-D points through calibrated, distorted cameras (paper §3).

Observations are pixel positions (OpenCV convention, lens distortion included) of the
same 3-D point in several cameras. :func:`triangulate` takes them as a ``(C, N, 2)``
array with NaN where a camera has no observation, and returns the world points that
minimise the reprojection error:

1. pixels are undistorted to normalised coordinates (:meth:`Camera.undistort_pixels`);
2. linear (DLT) estimate per point from every observing camera, batched SVD;
3. Gauss–Newton on the pixel reprojection error through the full lens model
   (:meth:`Camera.project`, central-difference Jacobians, batched over points);
4. optionally (``max_error``) the view with the largest error is dropped while the
   error exceeds ``max_error`` pixels and more than two views remain (one wrong
   click or one mismatched dot does not spoil the point).

Points with fewer than two observations are NaN and flagged ``n_views < 2``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..camera import Camera


@dataclass
class Triangulation:
    """``points`` (N, 3) world (NaN where impossible); ``n_views`` (N,) views used;
    ``used`` (C, N) bool; ``error`` (N,) RMS reprojection error in pixels over the used views
    (NaN where impossible); ``max_error`` (N,) the largest per-view error (pixels)."""

    points: np.ndarray
    n_views: np.ndarray
    used: np.ndarray
    error: np.ndarray
    max_error: np.ndarray

    @property
    def ok(self) -> np.ndarray:
        return self.n_views >= 2


def _dlt(cams: list[Camera], xn: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Linear triangulation from normalised coordinates ``xn`` (C, N, 2) where ``used`` (C, N)."""
    C, N = used.shape
    A = np.zeros((N, 2 * C, 4))
    for c, cam in enumerate(cams):
        P = np.concatenate([cam.R, cam.t[:, None]], axis=1)  # normalised camera matrix
        m = used[c]
        x = np.where(m, xn[c, :, 0], 0.0)
        y = np.where(m, xn[c, :, 1], 0.0)
        A[:, 2 * c] = (x[:, None] * P[2] - P[0]) * m[:, None]
        A[:, 2 * c + 1] = (y[:, None] * P[2] - P[1]) * m[:, None]
    # scale rows for conditioning (rows of a camera have similar magnitude already)
    _, _, vt = np.linalg.svd(A)
    Xh = vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    return X


def project_all(cams: list[Camera], X: np.ndarray) -> np.ndarray:
    """(C, N, 2) pixel projections of world points ``X`` (N, 3) into every camera."""
    return np.stack([cam.project(X)[0] for cam in cams])


def _residuals(cams, X, uv, used):
    pred = project_all(cams, X)
    r = np.where(used[..., None], pred - uv, 0.0)
    return np.nan_to_num(r, nan=1e3)


def refine(cams: list[Camera], X: np.ndarray, uv: np.ndarray, used: np.ndarray, iterations: int = 6,
           h: float = 1e-6) -> np.ndarray:
    """Gauss–Newton refinement of points ``X`` (N, 3) on the pixel reprojection error."""
    X = X.copy()
    for _ in range(iterations):
        r0 = _residuals(cams, X, uv, used)               # (C, N, 2)
        J = np.empty(r0.shape + (3,))
        for k in range(3):
            d = np.zeros(3)
            d[k] = h
            J[..., k] = (_residuals(cams, X + d, uv, used) - _residuals(cams, X - d, uv, used)) / (2 * h)
        J = J * used[..., None, None]
        Jf = J.transpose(1, 0, 2, 3).reshape(len(X), -1, 3)  # (N, 2C, 3)
        rf = r0.transpose(1, 0, 2).reshape(len(X), -1)       # (N, 2C)
        JtJ = np.einsum("nki,nkj->nij", Jf, Jf) + 1e-12 * np.eye(3)
        Jtr = np.einsum("nki,nk->ni", Jf, rf)
        ok = np.linalg.cond(JtJ) < 1e14
        step = np.zeros_like(X)
        step[ok] = np.linalg.solve(JtJ[ok], Jtr[ok][..., None])[..., 0]
        X -= step
        if np.nanmax(np.abs(step), initial=0.0) < 1e-10:
            break
    return X


def triangulate(cams: list[Camera], uv: np.ndarray, max_error: float | None = None,
                weights: np.ndarray | None = None, iterations: int = 6) -> Triangulation:
    """Triangulate N points from pixel observations ``uv`` (C, N, 2) (NaN = not observed).

    ``max_error`` (pixels): drop the worst view of a point while its error exceeds it and
    more than two views remain. ``weights`` is accepted for API symmetry and ignored
    (all observations count equally).
    """
    uv = np.asarray(uv, np.float64)
    if uv.ndim == 2:
        uv = uv[:, None]
    C, N = uv.shape[:2]
    if C != len(cams):
        raise ValueError(f"observations for {C} cameras, {len(cams)} cameras given")
    used = np.all(np.isfinite(uv), axis=-1)
    xn = np.full(uv.shape, np.nan)
    for c, cam in enumerate(cams):
        if used[c].any():
            xn[c, used[c]] = cam.undistort_pixels(uv[c, used[c]])
    X = np.full((N, 3), np.nan)
    err = np.full(N, np.nan)
    emax = np.full(N, np.nan)
    todo = np.flatnonzero(used.sum(0) >= 2)
    while todo.size:
        Xs = _dlt(cams, xn[:, todo], used[:, todo])
        Xs[~np.isfinite(Xs).all(1)] = 0.0
        Xs = refine(cams, Xs, uv[:, todo], used[:, todo], iterations)
        e = np.linalg.norm(project_all(cams, Xs) - uv[:, todo], axis=-1)
        e = np.where(np.isfinite(e), e, 1e6)
        e = np.where(used[:, todo], e, np.nan)
        X[todo] = Xs
        err[todo] = np.sqrt(np.nanmean(e ** 2, axis=0))
        emax[todo] = np.nanmax(e, axis=0)
        if max_error is None:
            break
        drop = (emax[todo] > max_error) & (used[:, todo].sum(0) > 2)
        if not drop.any():
            break
        worst = np.nanargmax(np.where(np.isfinite(e), e, -1.0), axis=0)
        used[worst[drop], todo[drop]] = False
        todo = todo[drop]
    nv = used.sum(0)
    X[nv < 2] = np.nan
    err[nv < 2] = np.nan
    emax[nv < 2] = np.nan
    used[:, nv < 2] = False
    return Triangulation(X, nv, used, err, emax)
