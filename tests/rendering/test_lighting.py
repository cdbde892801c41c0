import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from mifacerf import environment as E
from mifacerf.rendering.lighting import RotatedLightBasis
from mifacerf.rig import LightStage


@pytest.fixture(scope="module")
def setup(mi):
    ls = LightStage.semicircular_arm(8, 8)
    env = E.generated("gradient", 32)
    return ls, env, RotatedLightBasis(env, ls.directions, n_theta=48, grid_step_deg=3.0)


def reference(env, directions, R, mi):
    """L_l(R) = ∫_cell E(Rᵀω) dω by a fine quadrature, evaluating Mitsuba's envmap at Rᵀω."""
    qd, qw = E.sphere_quadrature(384)
    _, cell = cKDTree(directions).query(qd)
    rad = E.evaluate_emitter(mi.load_dict(env.mitsuba_dict()), qd @ R)
    out = np.zeros((len(directions), 3))
    np.add.at(out, cell, rad * qw[:, None])
    return out


def test_identity_is_exact(setup):
    ls, env, rb = setup
    np.testing.assert_array_equal(rb.rotated(np.eye(3)[None])[0], rb.identity)
    np.testing.assert_allclose(rb.identity, E.light_basis(env, ls.directions, n_theta=256))


@pytest.mark.parametrize("deg", [3.0, 20.0, 70.0])
def test_rotated_matches_reference(setup, mi, deg):
    ls, env, rb = setup
    R = Rotation.from_rotvec(np.array([0.3, 0.9, -0.3]) / np.linalg.norm([0.3, 0.9, -0.3]) * np.radians(deg)).as_matrix()
    got = rb.rotated(R[None])[0]
    ref = reference(env, ls.directions, R, mi)
    err = np.abs(got - ref).sum() / ref.sum()
    assert err < 0.03, err
    # and it is really rotated: the unrotated weights are further off for large angles
    if deg > 10:
        assert np.abs(rb.identity - ref).sum() / ref.sum() > 2 * err


def test_energy_conserved_and_continuous(setup):
    ls, env, rb = setup
    rv = np.linspace(0, 0.2, 41)[:, None] * np.array([[0.0, 1.0, 0.2]])
    out = rb.rotated(Rotation.from_rotvec(rv).as_matrix())
    total = out.sum(axis=1)
    np.testing.assert_allclose(total, np.broadcast_to(total[0], total.shape), rtol=0.02)
    steps = np.abs(np.diff(out, axis=0)).sum(axis=(1, 2)) / out[0].sum()
    assert steps.max() < 0.02  # 0.3° steps never jump
    assert (out >= 0).all()
