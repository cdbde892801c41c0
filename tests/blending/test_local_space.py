"""PCA of deformation vectors and the paper's residual-threshold choice of m."""
import numpy as np
import pytest

from mifacerf.blending.local_space import choose_dimension, fit_local_space


def data_of_rank(r, n=12, K=5, noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    base = rng.normal(size=(K, 3))
    dirs = rng.normal(size=(r, K, 3))
    coef = rng.normal(size=(n, r)) * 1e-2
    D = base + np.einsum("nr,rkc->nkc", coef, dirs) + noise * rng.normal(size=(n, K, 3))
    return D


@pytest.mark.parametrize("r", [0, 1, 2, 3])
def test_rank_gives_dimension(r):
    D = data_of_rank(r)
    sp = fit_local_space(D, np.ones(5, bool), residual_threshold=1e-9, max_dim=3)
    assert sp.m == r
    # the coordinates reproduce the data exactly (no residual)
    assert np.allclose(sp.reconstruct(sp.coords), D, atol=1e-12)
    assert np.allclose(sp.project(D), sp.coords, atol=1e-9)


def test_dimension_is_capped_and_threshold_monotone():
    D = data_of_rank(6, noise=1e-4)
    ms = [fit_local_space(D, np.ones(5, bool), thr, 3).m for thr in (0.0, 1e-5, 1e-3, 1.0)]
    assert ms[0] == 3 and ms[-1] == 0
    assert all(a >= b for a, b in zip(ms, ms[1:]))


def test_residual_definition():
    sig2 = np.array([4.0, 1.0, 0.25, 0.0625])
    m, res = choose_dimension(sig2, n=4, count=1, residual_threshold=0.3, max_dim=3)
    # residual(k) = sqrt(sum_{j>=k} sigma_j^2 / (n * count))
    assert np.allclose(res, np.sqrt(np.cumsum(sig2[::-1])[::-1] / 4))
    assert m == 2                                  # res = [1.15, 0.57, 0.28, 0.125]
    assert choose_dimension(sig2, n=2, count=2, residual_threshold=0.3, max_dim=3)[0] == 1   # m <= n - 1


def test_padding_is_ignored():
    D = data_of_rank(2, K=5)
    Dp = np.concatenate([D, 1e3 * np.ones((D.shape[0], 2, 3))], axis=1)
    mask = np.array([True] * 5 + [False] * 2)
    a = fit_local_space(D, np.ones(5, bool), 1e-9, 3)
    b = fit_local_space(Dp, mask, 1e-9, 3)
    assert a.m == b.m == 2
    assert np.allclose(np.abs(a.coords), np.abs(b.coords), atol=1e-9)
    assert np.all(b.basis[:, 5:] == 0)


def test_single_source():
    sp = fit_local_space(np.ones((1, 4, 3)), np.ones(4, bool), 0.0, 3)
    assert sp.m == 0 and sp.coords.shape == (1, 0) and sp.scale == 1.0
