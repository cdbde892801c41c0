"""Spherical harmonics (rendering/ivanic1996.py) and the ``sh`` compression method (rendering/sh_fields.py)."""
import itertools

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from mifacerf.environment import Environment, sphere_quadrature
from mifacerf.rendering.ivanic1996 import n_coefficients, real_sh, rotate_coefficients, sh_rotation
from mifacerf.rendering.sh_fields import cell_integrals, compress_sh, environment_coefficients


@pytest.fixture(scope="module")
def quadrature():
    return sphere_quadrature(192)


def test_real_sh_are_orthonormal_and_band_one_is_y_z_x(quadrature):
    qd, qw = quadrature
    Y = real_sh(qd, 5)
    G = (Y * qw[:, None]).T @ Y
    np.testing.assert_allclose(G, np.eye(n_coefficients(5)), atol=2e-4)
    d = np.array([[0.6, 0.0, 0.8], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]])
    np.testing.assert_allclose(real_sh(d, 1)[:, 1:], np.sqrt(3 / (4 * np.pi)) * d[:, [1, 2, 0]], atol=1e-12)
    np.testing.assert_allclose(real_sh(d, 0), 0.5 / np.sqrt(np.pi))


@pytest.mark.parametrize("order", [1, 2, 5])
def test_rotation_matches_projection_of_the_turned_function(quadrature, order):
    """D(R) a are the coefficients of f(Rᵀ ω) (the oracle: project the turned function directly)."""
    qd, qw = quadrature
    rng = np.random.default_rng(order)
    a = rng.normal(size=(n_coefficients(order), 2))
    R = Rotation.random(4, random_state=order).as_matrix()
    mine = rotate_coefficients(a, R, order)
    for k, Rk in enumerate(R):
        turned = real_sh(qd @ Rk, order) @ a          # f(Rᵀ ω), ω as rows: Rᵀ ω = ω R
        proj = (real_sh(qd, order) * qw[:, None]).T @ turned
        np.testing.assert_allclose(mine[k], proj, atol=2e-3)


def test_rotation_matrices_are_orthogonal_compose_and_keep_the_identity():
    R1, R2 = Rotation.random(2, random_state=3).as_matrix()
    for l, (D1, D2, D12, I) in enumerate(zip(sh_rotation(R1[None], 4), sh_rotation(R2[None], 4),
                                             sh_rotation((R1 @ R2)[None], 4), sh_rotation(np.eye(3)[None], 4))):
        np.testing.assert_allclose(D1[0] @ D1[0].T, np.eye(2 * l + 1), atol=1e-10)
        np.testing.assert_allclose(D1[0] @ D2[0], D12[0], atol=1e-10)
        np.testing.assert_allclose(I[0], np.eye(2 * l + 1), atol=1e-12)
    # reshaping the input does not change the result
    R = Rotation.random(6, random_state=4).as_matrix()
    np.testing.assert_allclose(sh_rotation(R.reshape(2, 3, 3, 3), 3)[3], sh_rotation(R, 3)[3])


def test_bad_values_do_not_crash():
    vals = [-1.0, 0.0, 1.0, np.inf, -np.inf, np.nan]
    d = np.array(list(itertools.product(vals, repeat=3)))
    with np.errstate(all="ignore"):
        Y = real_sh(d, 3)
        D = sh_rotation(np.broadcast_to(d[:, None, :], (len(d), 3, 3)), 3)
    assert Y.shape == (len(d), 16) and D[3].shape == (len(d), 7, 7)
    with pytest.raises(ValueError, match="order"):
        real_sh(d, -1)


def test_cell_integrals_and_environment_coefficients_integrate_the_sphere():
    dirs = Rotation.random(40, random_state=5).apply([0.0, 0.0, 1.0])
    M = cell_integrals(dirs, 3, n_theta=128)
    assert M.shape == (40, 16)
    # the cells tile the sphere: Σ_l ∫_cell Y_00 = √(4π), the other bands integrate to 0
    np.testing.assert_allclose(M.sum(0)[0], np.sqrt(4 * np.pi), rtol=1e-6)
    np.testing.assert_allclose(M.sum(0)[1:], 0.0, atol=5e-4)   # the 128-row lat-long quadrature's error
    env = Environment(np.full((64, 128, 3), 2.0, np.float32), "constant")
    e = environment_coefficients(env, 3, n_theta=128)
    np.testing.assert_allclose(e[0], 2.0 * np.sqrt(4 * np.pi), rtol=1e-5)
    np.testing.assert_allclose(e[1:], 0.0, atol=1e-3)   # quadrature error, 1e-4 of e[0]
    # a reflectance function constant over the lights: SH lighting equals the exact sum at any order
    rf = np.full((3, 40, 3), 0.25, np.float32)
    a = compress_sh(rf, [1, 3], dirs)
    assert a[1]["coeff"].shape == (3, 4, 3) and a[3]["coeff"].shape == (3, 16, 3)
    lit = np.einsum("njc,jc->nc", a[3]["coeff"].astype(np.float64), rotate_coefficients(e, np.eye(3)[None], 3)[0])
    np.testing.assert_allclose(lit, 0.25 * 2.0 * 4 * np.pi, rtol=2e-3)
    # back to the lights (each cell's average of the expansion): exact for the constant function
    from mifacerf.rendering.compression import reconstruct

    np.testing.assert_allclose(reconstruct(a[3], dirs), 0.25, atol=1e-4)
    with pytest.raises(ValueError, match="light directions"):
        reconstruct(a[3])


def test_sh_render_converges_to_exact(tmp_path_factory, mi):
    """compress --method sh writes <cam>.sh<order>.npz for every field; the render approaches the exact path as
    the order grows, with the per-vertex rotation applied in the SH domain."""
    from mifacerf import environment as E
    from mifacerf.rendering.build import build_model
    from mifacerf.rendering.compression import compress_model, compressed_path
    from mifacerf.rendering.model import Model
    from mifacerf.rendering.renderer import Renderer

    from helpers.toy import make_toy

    root = tmp_path_factory.mktemp("toysh")
    cap = make_toy(root, names=("neutral", "stretch"), size=40, n_pos=6, n_str=5, truth_registration=True).capture
    build_model(cap, root / "model")
    model = Model(root / "model")
    compress_model(model, [1, 6], progress=False, method="sh")
    model = Model(root / "model")
    assert model.meta["compressed"]["sh"] == [1, 6]
    assert compressed_path(model.root, "stretch", model.cameras[0].name, 6, "sh").exists()
    env = E.generated("sky", 32)
    W = np.full((model.n_vertices, 2), 0.5)
    target = 0.5 * (model.vertices[0] + model.vertices[1])
    cam = model.cameras[1]
    ref = Renderer(model).render(target, W, cam, env, spp=2)
    m = ref[..., 3] > 0.999
    assert m.sum() > 200

    def psnr(img):
        return 10 * np.log10(ref[..., :3][m].max() ** 2 / ((img - ref)[..., :3][m] ** 2).mean())

    low, high = (psnr(Renderer(model, method="sh", rank=k).render(target, W, cam, env, spp=2)) for k in (1, 6))
    assert high > low + 3 and high > 35, (low, high)
