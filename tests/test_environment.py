import numpy as np
import pytest

from mifacerf import environment as E
from mifacerf.rig import LightStage


def _spot_map(d, h=32, radiance=50.0):
    """A dark map with one bright texel in world direction d."""
    data = np.full((h, 2 * h, 3), 0.01, np.float32)
    u, v = E.direction_to_uv(np.asarray(d, float))
    data[int(v * h), int(u * 2 * h)] = radiance
    return E.Environment(data, "spot")


def test_uv_direction_round_trip(rng):
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    np.testing.assert_allclose(E.uv_to_direction(E.direction_to_uv(d)), d, atol=1e-12)


def test_documented_landmarks():
    uv = E.direction_to_uv(np.array([[0, 1, 0], [0, 0, 1], [1, 0, 0], [-1, 0, 0], [0, 0, -1.0]]))
    assert uv[0, 1] == pytest.approx(0.0)               # up = top row
    np.testing.assert_allclose(uv[1], [0.5, 0.5])        # +Z (front of the face) = centre
    np.testing.assert_allclose(uv[2], [0.25, 0.5])       # +X at u = 1/4
    np.testing.assert_allclose(uv[3], [0.75, 0.5])       # -X at u = 3/4
    assert uv[4, 0] in (0.0, 1.0) or uv[4, 0] == pytest.approx(0.0)


def test_convention_agrees_with_mitsuba_envmap(mi):
    """Mitsuba's envmap, loaded from our array, is brightest where our convention says."""
    d = np.array([0.5, 0.3, 0.81])
    d /= np.linalg.norm(d)
    env = _spot_map(d)
    emitter = mi.load_dict(env.mitsuba_dict())
    qd, _ = E.sphere_quadrature(64)
    rad = E.evaluate_emitter(emitter, qd).sum(axis=1)
    assert np.degrees(np.arccos(qd[rad.argmax()] @ d)) < 6.0


def test_rotation_matches_mitsuba_to_world(mi):
    """Rotating our map by R equals Mitsuba's envmap with to_world = R (the rotation test)."""
    from scipy.spatial.transform import Rotation

    env = E.generated("gradient", 32)
    R = Rotation.from_euler("yxz", [70, 25, -10], degrees=True).as_matrix()
    ours = E.Environment(env.rotated(R).data, "rot")
    T = np.eye(4)
    T[:3, :3] = R
    emitter = mi.load_dict({**env.mitsuba_dict(), "to_world": mi.ScalarTransform4f(T)})
    qd, _ = E.sphere_quadrature(32)
    ref = E.evaluate_emitter(emitter, qd)
    got = E.evaluate_emitter(mi.load_dict(ours.mitsuba_dict()), qd)
    rel = np.abs(got - ref).mean() / ref.mean()
    assert rel < 0.03, rel
    # and rotating by R^T undoes it
    back = ours.rotated(R.T)
    assert np.abs(back.data - env.data).mean() / env.data.mean() < 0.03


def test_light_basis_conserves_energy_and_localises():
    ls = LightStage.semicircular_arm(12, 10)
    env = E.generated("interior", 64)
    w = E.light_basis(env, ls.directions, n_theta=256)
    np.testing.assert_allclose(w.sum(axis=0), env.total_power(), rtol=5e-3)
    # a spot lands on the light nearest to it
    d = ls.directions[37] * 0.9 + ls.directions[38] * 0.1
    d /= np.linalg.norm(d)
    ws = E.light_basis(_spot_map(d, h=64, radiance=1000.0), ls.directions, n_theta=256)
    assert ws.sum(axis=1).argmax() == 37


def test_constant_environment_gives_solid_angles(mi):
    ls = LightStage.semicircular_arm(8, 6)
    w = E.light_basis(mi.load_dict({"type": "constant", "radiance": {"type": "rgb", "value": 2.0}}),
                      ls.directions, n_theta=512)
    np.testing.assert_allclose(w[:, 0], 2.0 * ls.solid_angles, rtol=0.02)


@pytest.mark.parametrize("name", sorted(E.GENERATORS))
def test_generated_environments_valid(name):
    env = E.generated(name, 32)
    assert env.data.shape == (32, 64, 3)
    assert np.isfinite(env.data).all() and env.data.min() >= 0 and env.data.max() > 0
    # the sky is brighter above the horizon than below
    if name in ("sky", "gradient"):
        assert env.data[:16].mean() > env.data[16:].mean()


def test_bad_environment_maps(tmp_path):
    with pytest.raises(E.EnvironmentError_, match="twice as wide"):
        E.Environment(np.ones((10, 10, 3)))
    with pytest.raises(E.EnvironmentError_, match="NaN"):
        E.Environment(np.full((4, 8, 3), np.nan))
    with pytest.raises(E.EnvironmentError_, match="negative"):
        E.Environment(-np.ones((4, 8, 3)))
    with pytest.raises(Exception, match="missing"):
        E.Environment.load(tmp_path / "none.exr")
    with pytest.raises(ValueError, match="unknown generated"):
        E.generated("moon")


def test_sample_emitter_lays_texels_out_as_mitsubas_envmap_reads_them(mi, rng):
    """An envmap of an H-row map, sampled back at H rows with one sample a texel, is the map again (Mitsuba's
    own lookup is the oracle; rows on the poles excepted: there Mitsuba has one direction for every column) —
    at the texel centres of latlong_grid (rows at (j + 1/2) / H) it is not."""
    H = 24
    data = rng.random((H, 2 * H, 3)).astype(np.float32)
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(data)})
    got = E.sample_emitter(emitter, H, sub=1)
    assert got.shape == data.shape and got.dtype == np.float32
    np.testing.assert_allclose(got[1:-1], data[1:-1], atol=1e-5)
    dirs, _ = E.latlong_grid(H)
    centres = E.evaluate_emitter(emitter, dirs.reshape(-1, 3)).reshape(data.shape)
    assert np.abs(centres[1:-1] - data[1:-1]).mean() > 0.05          # the other layout: not the map
    with pytest.raises(ValueError, match="height must be >= 2"):
        E.sample_emitter(emitter, 1)


def test_sample_emitter_keeps_light_smaller_than_a_texel(mi, rng):
    """A fine map (256 rows) with small bright windows, sampled at 32 rows: the light-stage weights of the result
    (what the facerf integrator lights with) hold the emitter's own light — total to 0.5 %, each light within
    20 % of the brightest (the coarse texels blur a window across neighbouring cells) — with the texel means;
    sampled at one point a texel, three quarters of the light are lost between the points."""
    h = 256
    data = np.full((h, 2 * h, 3), 0.02, np.float32)
    for r, c in ((20, 100), (60, 300), (110, 37), (150, 450), (230, 222)):  # 2 x 2 texels, 1/16 of a coarse texel
        data[r:r + 2, c:c + 2] = 400.0
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(data)})
    D = rng.normal(size=(60, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    ref = E.light_basis(emitter, D)
    means = E.light_basis(E.Environment(E.sample_emitter(emitter, 32), "means"), D)
    assert abs(means.sum() / ref.sum() - 1) < 0.005, means.sum() / ref.sum()
    assert np.abs(means - ref).max() / ref.max() < 0.2
    point = E.light_basis(E.Environment(E.sample_emitter(emitter, 32, sub=1), "points"), D)
    assert point.sum() / ref.sum() < 0.5
