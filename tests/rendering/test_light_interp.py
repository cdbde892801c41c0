import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from mifacerf.jitarrays import from_jit, to_jit
from mifacerf.rendering.light_interp import LightInterpolator
from mifacerf.rig import LightStage


@pytest.fixture(scope="module")
def interp():
    return LightInterpolator(LightStage.semicircular_arm(8, 6).directions, grid_height=64)


def test_exact_at_captured_directions(interp):
    idx, w = interp.weights(interp.directions)
    dense = np.zeros((len(idx), interp.n))
    np.add.at(dense, (np.arange(len(idx))[:, None].repeat(3, 1), idx), w)
    np.testing.assert_allclose(dense, np.eye(interp.n), atol=1e-9)


SHARED = LightInterpolator(LightStage.semicircular_arm(8, 6).directions, grid_height=64)


@settings(max_examples=100, deadline=None)
@given(st.floats(0.01, 3.13), st.floats(-3.14, 3.14))
def test_weights_reconstruct_direction_and_are_continuous(theta, phi):
    interp = SHARED
    d = np.array([np.sin(theta) * np.sin(phi), np.cos(theta), np.sin(theta) * np.cos(phi)])
    idx, w = interp.weights(d[None])
    assert np.all(w >= 0) and w.sum() == pytest.approx(1.0)
    recon = (w[0, :, None] * interp.directions[idx[0]]).sum(0)
    recon /= np.linalg.norm(recon)
    assert np.degrees(np.arccos(np.clip(recon @ d, -1, 1))) < 4.0  # inside (or at the edge of) its triangle


def test_drjit_agrees_with_numpy(interp, mi, rng):
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    idx, w = interp.weights(d)
    ids_j, w_j = interp.weights_jit(to_jit(mi.Vector3f, d.T))
    idx_j = np.stack([np.asarray(i) for i in ids_j], 1)
    wj = np.stack([np.asarray(x) for x in w_j], 1)
    dense = np.zeros((500, interp.n))
    dense_j = np.zeros((500, interp.n))
    np.add.at(dense, (np.arange(500)[:, None].repeat(3, 1), idx), w)
    np.add.at(dense_j, (np.arange(500)[:, None].repeat(3, 1), idx_j), wj)
    np.testing.assert_allclose(dense_j, dense, atol=2e-4)


def test_degenerate_layout_uses_nearest():
    circle = np.stack([np.cos(np.linspace(0, 2 * np.pi, 7)[:-1]), np.zeros(6), np.sin(np.linspace(0, 2 * np.pi, 7)[:-1])], 1)
    li = LightInterpolator(circle)
    assert li.nearest_only
    idx, w = li.weights(np.array([[0.9, 0.1, 0.05]]))
    assert idx[0, 0] == 0 and w[0, 0] == 1.0


@pytest.mark.parametrize("n_lights", [5, 12, 48, 150])
def test_lookup_grid_by_its_definition(n_lights):
    """The lookup grid (vectorised since 2026-12-03) is what its definition says, computed plainly: per
    cell the triangle with the largest smallest gnomonic barycentric among those not antipodal, and the
    first four distinct lights nearest to the cell's centre, corners and edge midpoints, repeated to four."""
    from mifacerf.environment import latlong_grid, uv_to_direction
    from mifacerf.rendering.light_interp import LightInterpolator

    rng = np.random.default_rng(n_lights)
    d = rng.standard_normal((n_lights, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    li = LightInterpolator(d, grid_height=12)
    dirs, _ = latlong_grid(12)
    dirs = dirs.reshape(-1, 3)
    for cell in range(len(dirs)):
        lam = li.inverse @ dirs[cell]                                     # (M, 3)
        score = np.where(lam.sum(1) > 0, lam.min(1), -np.inf)
        assert score[li.grid[cell]] >= score.max() - 1e-12
        assert score[li.grid[cell]] >= -1e-9                              # it holds the cell's centre
    h, w = 12, 24
    for cell in rng.choice(h * w, 40, replace=False):
        y, x = divmod(int(cell), w)
        near = [int(np.argmax(uv_to_direction(np.array([[(x + dx) / w, np.clip((y + dy) / h, 1e-6, 1 - 1e-6)]]))
                              @ d.T)) for dy in (0.0, 0.5, 1.0) for dx in (0.0, 0.5, 1.0)]
        u = list(dict.fromkeys(near))[:4]
        assert li.candidates[cell].tolist() == (u * 4)[:4]
