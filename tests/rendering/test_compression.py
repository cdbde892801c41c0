import numpy as np
import pytest

from mifacerf import environment as E
from mifacerf.rendering.compression import compress_field, compress_model, reconstruct


def test_pca_matches_svd_and_is_exact_at_full_rank(rng):
    L = 10
    latent = rng.random((500, 4))
    mix = rng.random((4, L * 3))
    rf = (latent @ mix).reshape(500, L, 3).astype(np.float32)
    full = compress_field(rf, rank=4)  # the data has rank 4 around its mean (at most 4)
    np.testing.assert_allclose(reconstruct(full), rf, atol=2e-3)  # float16 coefficients
    # rank-1 error equals the SVD's optimal rank-1 residual
    X = rf.reshape(500, -1).astype(np.float64)
    Xc = X - X.mean(0)
    s = np.linalg.svd(Xc, compute_uv=False)
    one = compress_field(rf, rank=1)
    resid = ((reconstruct(one).reshape(500, -1) - X) ** 2).sum()
    assert resid == pytest.approx((s[1:] ** 2).sum(), rel=0.02)


def test_degenerate_fields():
    empty = compress_field(np.zeros((0, 5, 3), np.float32), 4)
    assert empty["coeff"].shape == (0, 0)
    const = compress_field(np.ones((20, 5, 3), np.float32), 4)
    np.testing.assert_allclose(reconstruct(const), 1.0, atol=1e-6)
    assert np.isfinite(const["basis"]).all()


def test_compressed_render_converges_to_exact(tmp_path_factory, mi):
    from mifacerf.rendering.build import build_model
    from mifacerf.rendering.model import Model
    from mifacerf.rendering.renderer import Renderer

    from helpers.toy import make_toy

    root = tmp_path_factory.mktemp("toypca")
    cap = make_toy(root, names=("neutral", "stretch"), size=40, n_pos=6, n_str=5, truth_registration=True).capture
    build_model(cap, root / "model")
    m = Model(root / "model")
    for k in (2, 8, 30):
        compress_model(m, k)
    env = E.generated("interior", 32)
    W = np.zeros((m.n_vertices, 2))
    W[:, 1] = 1
    exact = Renderer(m).render(m.vertices[1], W, m.cameras[0], env, spp=1)
    mask = exact[..., 3] > 0.999

    def psnr(rank):
        img = Renderer(m, method="pca", rank=rank).render(m.vertices[1], W, m.cameras[0], env, spp=1)
        return 10 * np.log10(exact[..., :3][mask].max() ** 2 / ((img - exact)[..., :3][mask] ** 2).mean())

    low, mid, high = psnr(2), psnr(8), psnr(30)
    assert low < mid < high  # more coefficients, less error (rank 3L = 90 would be exact)
    assert high > 40  # measured 41.3 dB


def test_compressed_fields_by_name(toy_model, tmp_path):
    """Every method of COMPRESSION_METHODS through its name: the compressing ones write files under it
    (into a copy of the toy model), and the renderer lights each by it, close to the exact path."""
    import shutil

    from mifacerf.rendering import compression as C
    from mifacerf.rendering.model import Model
    from mifacerf.rendering.renderer import Renderer

    shutil.copytree(toy_model.root, tmp_path / "model")
    toy_model = Model(tmp_path / "model")

    env = E.generated("gradient", 16)
    W = np.zeros((toy_model.n_vertices, len(toy_model.expressions)))
    W[:, 0] = 1
    exact = Renderer(toy_model).render(toy_model.vertices[0], W, toy_model.cameras[0], env, spp=1)
    for method in C.COMPRESSION_METHODS:
        if C.COMPRESSION_METHODS[method].compress is not None:
            C.compress_model(toy_model, 30, method=method)
            assert 30 in toy_model.meta["compressed"][method]
            assert C.compressed_path(toy_model.root, toy_model.expressions[0], toy_model.cameras[0].name, 30,
                                     method).exists()
        img = Renderer(toy_model, method=method, rank=30).render(toy_model.vertices[0], W, toy_model.cameras[0],
                                                                 env, spp=1)
        cov = exact[..., 3] > 0.999
        err = ((img - exact)[..., :3][cov] ** 2).mean()
        assert err == 0 or 10 * np.log10(exact[..., :3][cov].max() ** 2 / err) > 35.0, method
    with pytest.raises(ValueError, match="unknown compression method"):
        Renderer(toy_model, method="svd")
    with pytest.raises(ValueError, match="unknown light basis method"):
        Renderer(toy_model, basis="sh")
    with pytest.raises(ValueError, match="light subset"):
        Renderer(toy_model, method="pca", lights=[0, 1])
