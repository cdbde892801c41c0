"""BlendModel end to end: the Dr.Jit evaluator against the reference, and the stability properties."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from mifacerf.blending import BlendModel, local_rotations
from mifacerf.blending.toy import grid_mesh, random_sources, toy_subject



def dense(ids, w, n):
    """(T, F, K) sparse → (T, F, n) dense, float64."""
    out = np.zeros(ids.shape[:2] + (n,))
    t, f = np.meshgrid(np.arange(ids.shape[0]), np.arange(ids.shape[1]), indexing="ij")
    for k in range(ids.shape[2]):
        np.add.at(out, (t, f, ids[..., k]), w[..., k])
    return out

SET = settings(max_examples=15, deadline=None)


def targets(sub, params, rng, T=12, outside=1.6, rigid=True):
    """Random blends of the sources' parameters, a third of them pushed outside the set."""
    a = rng.dirichlet(np.ones(len(params)) * 0.5, size=T)
    p = a @ params
    p[: T // 3] *= outside
    rot = rng.normal(size=(T, 3)) * 0.1 if rigid else None
    sh = rng.normal(size=(T, 3)) * 0.01 if rigid else None
    return sub.pose(p, rot, sh)


def check_valid(sw, n_src):
    assert sw.indices.dtype == np.int32 and sw.weights.dtype == np.float32
    assert sw.indices.shape == sw.weights.shape and sw.indices.shape[-1] == 4
    assert np.all(np.isfinite(sw.weights)) and np.all(sw.weights >= 0)
    assert np.allclose(sw.weights.sum(-1), 1, atol=1e-6)
    assert np.all((sw.indices >= 0) & (sw.indices < n_src))
    assert np.all(np.diff(sw.weights, axis=-1) <= 0)                  # sorted, decreasing


def test_drjit_matches_reference_float64(toy, model):
    sub, S, params = toy
    X = targets(sub, params, np.random.default_rng(0), T=20)
    ri, rw = model.fiducial_weights(X, method="reference")
    di, dw = model.fiducial_weights(X, method="drjit", precision="float64")
    assert np.abs(dense(ri, rw, len(S)) - dense(di, dw, len(S))).max() < 1e-7
    assert set(np.unique(model.dims)) >= {3}


def test_drjit_matches_reference_with_culling(toy, culled_model):
    sub, S, params = toy
    X = targets(sub, params, np.random.default_rng(1), T=10)
    ri, rw = culled_model.fiducial_weights(X, method="reference")
    di, dw = culled_model.fiducial_weights(X, method="drjit", precision="float64")
    assert np.abs(dense(ri, rw, len(S)) - dense(di, dw, len(S))).max() < 1e-7


@SET
@given(seed=st.integers(0, 2 ** 31), outside=st.sampled_from([1.0, 1.5, 3.0]))
def test_weights_valid(toy, model, seed, outside):
    sub, S, params = toy
    X = targets(sub, params, np.random.default_rng(seed), T=6, outside=outside)
    for precision in ("float32", "float64"):
        check_valid(model.weights(X, precision=precision), len(S))


@SET
@given(seed=st.integers(0, 2 ** 31), outside=st.sampled_from([1.6, 4.0]))
def test_float32_agrees_with_float64(toy, model, seed, outside):
    sub, S, params = toy
    X = targets(sub, params, np.random.default_rng(seed), T=6, outside=outside)
    a = model.dense_weights(X, precision="float64")
    b = model.dense_weights(X, precision="float32")
    # float32 carries ~1e-8 m of rounding in the local deformation; a weight moves by at most
    # (its Lipschitz constant) x (that), so the agreement is bounded by the vertex's conditioning
    lip = model.weight_lipschitz()
    assert np.all(np.abs(a - b).max(axis=(0, 2)) <= 2e-8 * lip + 1e-5)
    well = lip < 1e5
    assert well.sum() > 10 and np.abs(a - b)[:, well].max() < 2e-3
    # the blended source deformation (what rendering sees) agrees to far below a micrometre
    Dsrc = model.local_deformations(S)                               # (n, F, K, 3)
    ra = np.einsum("tfn,nfkc->tfkc", a, Dsrc)
    rb = np.einsum("tfn,nfkc->tfkc", b, Dsrc)
    assert np.abs(ra - rb).max() < 1e-7                              # metres


def test_float32_check_can_fail(toy, model):
    """The bound above is not vacuous: a 1e-6 m perturbation of the targets breaks it."""
    sub, S, params = toy
    X = targets(sub, params, np.random.default_rng(11), T=6)
    a = model.dense_weights(X, precision="float64")
    b = model.dense_weights(X + np.random.default_rng(0).normal(size=X.shape) * 1e-6, precision="float64")
    lip = model.weight_lipschitz()
    assert not np.all(np.abs(a - b).max(axis=(0, 2)) <= 2e-8 * lip + 1e-5)


@SET
@given(seed=st.integers(0, 2 ** 31))
def test_rigid_motion_of_target_is_invisible(toy, model, seed):
    sub, S, params = toy
    rng = np.random.default_rng(seed)
    X = targets(sub, params, rng, T=4)
    R = Rotation.random(random_state=seed).as_matrix()
    Y = X @ R.T + rng.normal(size=3) * 0.3
    a = model.dense_weights(X, precision="float64")
    b = model.dense_weights(Y, precision="float64")
    assert np.abs(a - b).max() < 1e-6


def test_rigid_check_can_fail(toy, model):
    """A non-rigid change (a scale) must change the weights: the invariance test is not vacuous."""
    sub, S, params = toy
    X = targets(sub, params, np.random.default_rng(3), T=4)
    a = model.dense_weights(X, precision="float64")
    b = model.dense_weights(X * 1.05, precision="float64")
    assert np.abs(a - b).max() > 1e-3


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_sources_reproduce_themselves(toy, model, precision):
    sub, S, params = toy
    n = len(S)
    sw = model.weights(S, precision=precision)
    lip = model.weight_lipschitz()
    # a source that is not a (near-)duplicate at a vertex gets weight 1 on itself there
    single = np.array([[np.sum(t.merged == t.merged[i]) == 1 for t in model.triangulations] for i in range(n)])
    assert single.mean() > 0.5
    tol = 1e-6 if precision == "float64" else 2e-8 * lip + 1e-4
    ok = (sw.indices[..., 0] == np.arange(n)[:, None]) & (sw.weights[..., 0] >= 1 - tol)
    assert np.all(ok[single])
    # every source's blend reproduces its local deformation (merged ones to within the duplicate tolerance)
    D = model.local_deformations(S)
    rec = np.einsum("tfn,nfkc->tfkc", sw.dense(n), D)
    cnt = model.nbhd.count[model.fiducials]
    rms = np.sqrt(np.sum((rec - D) ** 2, axis=(2, 3)) / cnt)
    assert rms[single].max() < (1e-9 if precision == "float64" else 5e-7)
    # a merged source differs from its representative by <= 2 dup_tol inside the PCA subspace and by
    # its own PCA residual outside it (<= sqrt(n) x the RMS residual threshold)
    assert rms.max() < 3 * model.params["dup_tol"] + np.sqrt(n) * model.params["residual_threshold"]


def test_reproduction_check_can_fail(toy, model):
    """Weights of a *different* source fail the reproduction criterion."""
    sub, S, params = toy
    sw = model.weights(np.roll(S, 1, axis=0))
    assert not np.all(sw.indices[..., 0] == np.arange(len(S))[:, None])


def test_m0_vertices_weight_the_neutral():
    V, F = grid_mesh(12, 10)
    rng = np.random.default_rng(0)
    far = V[:, 0] > 0.0                                # only the left half ever deforms
    S = []
    for i in range(8):
        X = V.copy()
        if i:
            X[~far] += rng.normal(size=3) * 3e-3 * np.exp(-((V[~far, :2] + 0.05) ** 2).sum(1) / 2e-3)[:, None]
            X = X @ Rotation.from_rotvec(rng.normal(size=3) * 0.1).as_matrix().T
        S.append(X)
    S = np.array(S)
    model = BlendModel.fit(S, 0, F, residual_threshold=1e-6)
    vd = model.vertex_dims()
    nb_far = np.array([np.all(far[model.nbhd.index[v, : model.nbhd.count[v]]]) for v in range(len(V))])
    assert np.all(vd[nb_far] == 0) and np.any(vd > 0)
    sw = model.weights(S[3:5] @ Rotation.from_rotvec([0.2, 0, 0]).as_matrix().T)
    assert np.all(sw.indices[:, nb_far, 0] == 0) and np.all(sw.weights[:, nb_far, 0] == 1)


def test_degenerate_sources_give_finite_results():
    V, F = grid_mesh(8, 6)
    rng = np.random.default_rng(1)
    base = np.stack([V + rng.normal(size=V.shape) * 2e-3 for _ in range(5)])
    R = Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix()
    S = np.concatenate([[V], base, base[:2], base[2:3] @ R.T + 0.01])      # exact and rigid duplicates
    model = BlendModel.fit(S, 0, F, residual_threshold=0.0)
    sw = model.weights(np.concatenate([S, base.mean(0, keepdims=True) * 1.01]), precision="float64")
    check_valid(sw, len(S))
    # duplicates map to the first of their cluster
    assert np.all(sw.indices[6, :, 0] == 1) and np.all(sw.indices[8, :, 0] == 3)
    # all sources identical: zero-variance neighbourhoods → m = 0, neutral
    same = np.stack([V] * 4)
    m0 = BlendModel.fit(same, 2, F)
    assert np.all(m0.dims == 0)
    sw = m0.weights(same[:1] + rng.normal(size=V.shape) * 1e-3)
    assert np.all(sw.indices[..., 0] == 2) and np.all(sw.weights[..., 0] == 1)


def test_culling_composes_with_vertex_weights(toy, culled_model):
    sub, S, params = toy
    kept = culled_model.kept
    assert set(kept) == set(sub.regions)
    assert all(0 in v for v in kept.values())
    assert any(len(v) < len(S) for v in kept.values())
    X = targets(sub, params, np.random.default_rng(5), T=8)
    sw = culled_model.weights(X)
    check_valid(sw, len(S))
    mem = culled_model.culling.membership
    names = culled_model.culling.names
    for v in range(culled_model.n_vertices):
        regs = [names[k] for k in np.nonzero(mem[v])[0]]
        allowed = set(np.arange(len(S))) if not regs else set().union(*[set(kept[r].tolist()) for r in regs])
        used = set(sw.indices[:, v][sw.weights[:, v] > 0].tolist())
        assert used <= allowed, (v, used - allowed)


def test_non_fiducial_vertices_are_interpolated(toy, model):
    sub, S, params = toy
    rng = np.random.default_rng(6)
    mask = rng.random(len(sub.neutral)) < 0.5
    part = BlendModel.fit(S, 0, sub.triangles, fiducial_mask=mask, residual_threshold=1e-5)
    X = targets(sub, params, rng, T=5)
    sw = part.weights(X, precision="float64")
    check_valid(sw, len(S))
    full = model.dense_weights(X, precision="float64")
    pd = sw.dense(len(S))
    assert np.abs(pd[:, mask] - full[:, mask]).max() < 1e-6              # fiducials unchanged
    # a non-fiducial vertex uses only sources of its interpolating fiducials
    fi, fw = part.fiducial_weights(X, precision="float64")
    for r, u in enumerate(part.interp_vertices[:10]):
        srcs = set(fi[:, part.interp_index[r]][fw[:, part.interp_index[r]] > 0].tolist())
        assert set(sw.indices[:, u][sw.weights[:, u] > 0].tolist()) <= srcs


def test_save_load_roundtrip(tmp_path, toy, culled_model):
    sub, S, params = toy
    X = targets(sub, params, np.random.default_rng(7), T=5)
    p = tmp_path / "blend.npz"
    culled_model.save(p)
    back = BlendModel.load(p)
    assert np.array_equal(back.dims, culled_model.dims)
    assert {k: v.tolist() for k, v in back.kept.items()} == {k: v.tolist() for k, v in culled_model.kept.items()}
    a = culled_model.weights(X, precision="float64")
    b = back.weights(X, precision="float64")
    assert np.array_equal(a.indices, b.indices) and np.array_equal(a.weights, b.weights)
    c = back.weights(X, method="reference")
    assert np.abs(c.dense(len(S)) - a.dense(len(S))).max() < 1e-6


def test_local_rotations():
    sub = toy_subject(8, 7, 3, seed=1)
    S, _ = random_sources(sub, 4, seed=2)
    from mifacerf.blending import neighbourhoods

    nb = neighbourhoods(sub.triangles, len(sub.neutral))
    R0 = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    tgt = S[2] @ R0.T + 1.0
    R = local_rotations(tgt, S[2], nb)
    assert R.shape == (len(sub.neutral), 3, 3)
    assert np.allclose(R, R0.T, atol=1e-10)               # takes the target's local pose to the source's
    R = local_rotations(S[1], S[2], nb.as_lists())
    assert np.allclose(np.linalg.det(R), 1) and not np.allclose(R, np.eye(3), atol=1e-3)
    Rb = local_rotations(np.stack([tgt, S[1]]), S[2], nb)   # batched over frames
    assert Rb.shape == (2,) + R.shape and np.allclose(Rb[0], R0.T, atol=1e-10)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_bad_targets_raise(model, toy, bad):
    sub, S, _ = toy
    X = S[:2].copy()
    X[1, 3, 0] = bad
    with pytest.raises(ValueError, match="non-finite"):
        model.weights(X)
    with pytest.raises(ValueError, match=r"\(n, 80, 3\)"):
        model.weights(S[:, :10])


def test_fit_argument_errors(toy):
    sub, S, _ = toy
    with pytest.raises(ValueError):
        BlendModel.fit(S, 99, sub.triangles)
    with pytest.raises(ValueError):
        BlendModel.fit(S, 0, sub.triangles, max_dim=4)
    with pytest.raises(ValueError):
        BlendModel.fit(S, 0, sub.triangles, fiducial_mask=np.zeros(len(sub.neutral), bool))
