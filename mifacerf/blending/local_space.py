"""Per-vertex PCA of the source deformation vectors and the choice of dimensionality (paper §5).

The paper chooses ``m`` "such that the sum square of the projections of all the
deformation vectors onto the n-m smallest eigenvectors falls below a threshold",
with ``m <= 3``.  We express that threshold as an RMS distance in **metres**, so
one value suits neighbourhoods of any size and any number of sources:

    residual(m) = sqrt( Σ_{k >= m} σ_k² / (n · |V|) )          (σ_k: singular values of the
                                                                 centred n × 3|V| data matrix)

and ``m`` is the smallest dimension with ``residual(m) <= residual_threshold``
(capped by ``max_dim`` and by ``n - 1``).  The paper's absolute threshold equals
``n · |V| · residual_threshold²``.  PCA is centred on the mean deformation
vector.  Coordinates are expressed in units of ``scale`` (the RMS spread along
the first principal axis), which keeps qhull well conditioned whatever the
physical size of the deformations.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["LocalSpace", "fit_local_space", "choose_dimension"]


@dataclass
class LocalSpace:
    """PCA of one vertex's source deformation vectors.

    Attributes
    ----------
    mean : ndarray ``(K, 3)``       mean deformation vector (zero on padding entries)
    basis : ndarray ``(m, K, 3)``   orthonormal principal directions (zero on padding)
    scale : float                  coordinate unit in metres (> 0)
    coords : ndarray ``(n, m)``     sources' coordinates ``<D - mean, basis> / scale``
    residuals : ndarray ``(max_dim + 1,)``  RMS residual (metres) for each candidate ``m``
    m : int                        chosen dimensionality
    """

    mean: np.ndarray
    basis: np.ndarray
    scale: float
    coords: np.ndarray
    residuals: np.ndarray
    m: int

    def project(self, D: np.ndarray) -> np.ndarray:
        """Coordinates ``(..., m)`` of deformation vectors ``D`` ``(..., K, 3)`` (orthogonal projection)."""
        return np.einsum("...kc,mkc->...m", D - self.mean, self.basis) / self.scale

    def reconstruct(self, z: np.ndarray) -> np.ndarray:
        """Deformation vectors ``(..., K, 3)`` of coordinates ``z`` ``(..., m)``."""
        return self.mean + np.einsum("...m,mkc->...kc", z * self.scale, self.basis)


def choose_dimension(sigma2: np.ndarray, n: int, count: int, residual_threshold: float, max_dim: int) -> tuple[int, np.ndarray]:
    """Smallest ``m <= max_dim`` whose RMS residual ``sqrt(Σ_{k>=m} σ_k² / (n·count))`` is <= the threshold.

    Returns ``(m, residuals)`` with ``residuals[k]`` the RMS residual of ``m = k``, ``k = 0..max_dim``.
    """
    s = np.zeros(max_dim + 1 + len(sigma2))
    s[: len(sigma2)] = sigma2
    tail = np.cumsum(s[::-1])[::-1]                     # tail[k] = Σ_{j>=k} σ_j²
    residuals = np.sqrt(np.maximum(tail[: max_dim + 1], 0.0) / max(n * count, 1))
    ok = np.nonzero(residuals <= residual_threshold)[0]
    m = int(ok[0]) if ok.size else max_dim
    return min(m, max(n - 1, 0)), residuals


def fit_local_space(D, mask, residual_threshold: float, max_dim: int = 3) -> LocalSpace:
    """PCA of ``n`` deformation vectors.

    Parameters
    ----------
    D : array_like, shape ``(n, K, 3)``
        Aligned neighbourhood positions of the ``n`` sources (metres).
    mask : array_like, shape ``(K,)`` bool
        Real (True) versus padding (False) entries.
    residual_threshold : float
        RMS residual in metres (see the module docstring).
    max_dim : int
        Upper bound on ``m`` (the paper uses 3; at most 3 here).
    """
    D = np.asarray(D, dtype=np.float64)
    mask = np.asarray(mask, dtype=bool)
    if D.ndim != 3 or D.shape[2] != 3 or D.shape[1] != mask.size:
        raise ValueError(f"D must have shape (n, K, 3) with K = {mask.size}; got {D.shape}")
    if not 0 <= max_dim <= 3:
        raise ValueError(f"max_dim must be in 0..3; got {max_dim}")
    n, K = D.shape[:2]
    D = np.where(mask[None, :, None], D, 0.0)
    mean = D.mean(axis=0)
    X = (D - mean).reshape(n, K * 3)
    # Eigen-decomposition of the small n x n Gram matrix (LAPACK's SVD of tiny matrices is pathologically
    # slow under a multi-threaded BLAS); the leading directions are re-orthonormalised.
    if n > 1:
        lam, U = np.linalg.eigh(X @ X.T)
        lam, U = np.maximum(lam[::-1], 0.0), U[:, ::-1]
    else:
        lam, U = np.zeros(0), np.zeros((1, 0))
    sigma2 = lam
    m, residuals = choose_dimension(sigma2, n, int(mask.sum()), residual_threshold, max_dim)
    m = min(m, int(np.count_nonzero(sigma2 > 1e-24 * max(float(sigma2[0]) if sigma2.size else 0.0, 1e-300))))
    Bm = X.T @ U[:, :m]                                          # (3K, m), columns ~ σ_k v_k
    if m:
        Bm, Rq = np.linalg.qr(Bm)
        Bm = Bm * np.sign(np.where(np.diag(Rq) == 0, 1.0, np.diag(Rq)))[None, :]
    basis = Bm.T.reshape(m, K, 3)
    # deterministic sign: the largest-magnitude component of each direction is positive
    for k in range(m):
        flat = basis[k].ravel()
        if flat[np.argmax(np.abs(flat))] < 0:
            basis[k] *= -1
    scale = float(np.sqrt(sigma2[0] / n)) if (sigma2.size and sigma2[0] > 0) else 1.0
    coords = (X @ basis.reshape(m, K * 3).T) / scale
    return LocalSpace(mean=mean, basis=basis, scale=scale, coords=coords, residuals=residuals, m=m)
