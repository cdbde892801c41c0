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


# ------------------------------------------------------------ the hat light basis (LIGHT_BASIS_METHODS["hat"])
OCTAHEDRON = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])


def test_hat_shares_a_direction_by_its_barycentric_coordinates():
    """A delta environment at ω = (1, 2, 3)/|.| lies in the octahedron's facet (+x, +y, +z) at the
    facet point (1, 2, 3)/6: its three lights share it 1/6, 2/6, 3/6; the Voronoi rule gives it to +z."""
    w = np.array([1.0, 2.0, 3.0])
    lights, shares = E.light_shares((w / np.linalg.norm(w))[None], OCTAHEDRON, "hat")
    got = dict(zip(lights[0].tolist(), shares[0].tolist()))
    assert set(got) == {0, 2, 4}
    np.testing.assert_allclose([got[0], got[2], got[4]], w / w.sum(), atol=1e-12)
    lights, shares = E.light_shares((w / np.linalg.norm(w))[None], OCTAHEDRON, "voronoi")
    assert lights.tolist() == [[4]] and shares.tolist() == [[1.0]]


def test_hat_shares_on_the_arm_are_barycentric(rng):
    """Any direction: three distinct lights, shares >= 0 summing to 1, whose combination of light
    directions points along the direction (its facet point); a light's own direction is all its own."""
    ls = LightStage.semicircular_arm(16, 12)
    q = rng.normal(size=(2000, 3))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    lights, shares = E.hat_shares(q, ls.directions)
    assert (shares >= 0).all()
    np.testing.assert_allclose(shares.sum(axis=1), 1.0, atol=1e-12)
    assert (np.sort(lights, axis=1)[:, 1:] != np.sort(lights, axis=1)[:, :-1]).all()
    p = np.einsum("nk,nkd->nd", shares, ls.directions[lights])
    np.testing.assert_allclose(np.cross(p, q), 0.0, atol=1e-12)
    assert (np.einsum("nd,nd->n", p, q) > 0).all()
    own, own_share = E.hat_shares(ls.directions, ls.directions)
    np.testing.assert_array_equal(own[np.arange(len(ls)), own_share.argmax(axis=1)], np.arange(len(ls)))
    np.testing.assert_allclose(own_share.max(axis=1), 1.0, atol=1e-9)


def test_constant_environment_integrates_the_same_under_both_rules(mi):
    """E = 2: the total is 2·4π under both rules; on the octahedron every light's hat and cell hold 4π/6."""
    const = mi.load_dict({"type": "constant", "radiance": {"type": "rgb", "value": 2.0}})
    ls = LightStage.semicircular_arm(8, 6)
    for method in E.LIGHT_BASIS_METHODS:
        w = E.light_basis(const, ls.directions, n_theta=256, method=method)
        np.testing.assert_allclose(w.sum(axis=0), 2.0 * 4 * np.pi, rtol=1e-4)
        w = E.light_basis(const, OCTAHEDRON, n_theta=256, method=method)
        np.testing.assert_allclose(w[:, 0], 2.0 * 4 * np.pi / 6, rtol=2e-3)


def test_hat_spreads_a_spot_over_its_triangle():
    """A one-texel spot lands on its octahedron facet's three lights (Voronoi: one light), barycentrically."""
    w = np.array([1.0, 2.0, 3.0])
    h = 128
    data = np.zeros((h, 2 * h, 3), np.float32)
    u, v = E.direction_to_uv(w / np.linalg.norm(w))
    data[int(v * h), int(u * 2 * h)] = 100.0
    env = E.Environment(data, "spot")
    hat = E.light_basis(env, OCTAHEDRON, n_theta=512, method="hat")[:, 0]
    vor = E.light_basis(env, OCTAHEDRON, n_theta=512)[:, 0]
    np.testing.assert_allclose(hat.sum(), vor.sum(), rtol=1e-9)
    assert np.count_nonzero(vor) == 1 and vor[4] > 0
    assert hat[[1, 3, 5]].max() == 0
    np.testing.assert_allclose(hat[[0, 2, 4]] / hat.sum(), w / w.sum(), atol=0.02)   # the texel's spread


def test_hat_without_a_triangulation_falls_back_to_the_nearest_light():
    q = np.array([[0.9, 0.1, 0.0], [0.1, 0.2, 0.95]])
    lights, shares = E.hat_shares(q / np.linalg.norm(q, axis=1, keepdims=True), np.eye(3))
    assert lights[:, 0].tolist() == [0, 2] and shares[:, 0].tolist() == [1.0, 1.0]


def test_rotated_hat_basis_is_anchored_and_conserves_energy(mi):
    ls = LightStage.semicircular_arm(8, 8)
    env = E.generated("gradient", 32)
    rb = RotatedLightBasis(env, ls.directions, n_theta=48, method="hat")
    np.testing.assert_allclose(rb.identity, E.light_basis(env, ls.directions, n_theta=256, method="hat"))
    vor = RotatedLightBasis(env, ls.directions, n_theta=48)
    assert np.abs(rb.identity - vor.identity).sum() > 0.05 * vor.identity.sum()   # a different basis
    R = Rotation.from_rotvec(np.array([[0.0, 0.5, 0.1], [0.3, 0.0, 0.0], [0.0, 1.2, 0.0]])).as_matrix()
    out = rb.rotated(R)
    np.testing.assert_allclose(out.sum(axis=1), np.broadcast_to(rb.identity.sum(axis=0), (3, 3)), rtol=0.02)
    qd, qw = E.sphere_quadrature(384)   # the reference: a fine quadrature of E(Rᵀω) h_l(ω)
    lights, shares = E.light_shares(qd, ls.directions, "hat")
    for r, got in zip(R, out):
        rad = E.evaluate_emitter(mi.load_dict(env.mitsuba_dict()), qd @ r)
        ref = np.zeros((len(ls), 3))
        for k in range(3):
            np.add.at(ref, lights[:, k], rad * (qw * shares[:, k])[:, None])
        assert np.abs(got - ref).sum() / ref.sum() < 0.03


def test_renderer_takes_the_light_basis_by_name(toy_model):
    """Renderer(basis=...) lights with that LIGHT_BASIS_METHODS rule: a captured expression seen from its
    own camera reproduces its field's texels relit by light_basis(..., method=...) of the same rule."""
    from mifacerf.rendering.renderer import Renderer

    env = E.generated("interior", 32)
    s, c = toy_model.expression_index("stretch"), 1
    cam, f = toy_model.cameras[c], toy_model.field(s, c)
    W = np.zeros((toy_model.n_vertices, len(toy_model.expressions)))
    W[:, s] = 1
    assert Renderer(toy_model).basis == E.DEFAULT_LIGHT_BASIS_METHOD == "voronoi"
    refs = {}
    for method in E.LIGHT_BASIS_METHODS:
        img = Renderer(toy_model, basis=method).render(toy_model.vertices[s], W, cam, env, spp=1)
        lit = np.einsum("nlc,lc->nc", np.asarray(f.rf, np.float64),
                        E.light_basis(env, toy_model.light_directions, method=method))
        got = img[f.pixels[:, 0], f.pixels[:, 1]]
        inside = got[:, 3] > 0.999
        assert inside.sum() > 0.8 * len(inside)
        err = ((got[inside, :3] - lit[inside]) ** 2).mean()
        assert 10 * np.log10(lit[inside].max() ** 2 / err) > 50.0, method   # the texels themselves
        refs[method] = lit
    assert np.abs(refs["hat"] - refs["voronoi"]).max() > 0.01 * refs["voronoi"].max()   # two different rules


def test_the_numba_node_blend_is_the_numpy_loops_bit_for_bit(setup, monkeypatch):
    """``rotated``'s trilinear blend of grid nodes through Numba (``_numba_kernels.trilinear_rows``) and
    through the NumPy loop (``MIFACERF_NUMBA_RELIGHT=0``): the same float64 values, to the bit, for
    rotations inside the grid, on its nodes and beyond it."""
    pytest.importorskip("numba")
    from scipy.spatial.transform import Rotation

    ls, env, rb = setup
    rng = np.random.default_rng(3)
    R = np.concatenate([Rotation.from_rotvec(rng.normal(scale=np.radians(8), size=(40, 3))).as_matrix(),
                        Rotation.from_rotvec([[np.radians(3), 0, 0], [0, np.radians(-6), 0]]).as_matrix(),
                        np.eye(3)[None]])
    monkeypatch.setenv("MIFACERF_NUMBA_RELIGHT", "0")
    plain = rb.rotated(R)
    monkeypatch.setenv("MIFACERF_NUMBA_RELIGHT", "1")
    np.testing.assert_array_equal(rb.rotated(R), plain)
