"""The captured self-visibility the material divides out (mifacerf.rendering.self_visibility)."""
import numpy as np


def _sphere(n=400):
    from scipy.spatial import ConvexHull

    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = np.pi * (1 + 5 ** 0.5) * k
    V = np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)
    F = ConvexHull(V).simplices
    # outward winding
    flip = np.einsum("ij,ij->i", np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), V[F].mean(1)) < 0
    F[flip] = F[flip][:, ::-1]
    return V, F


def test_a_convex_mesh_shadows_exactly_the_lights_behind_its_tangent_plane(mi):
    """On a sphere a vertex sees a light iff the light is in front of its tangent plane (away from grazing)."""
    from mifacerf.rendering.self_visibility import trace

    V, F = _sphere()
    rng = np.random.default_rng(0)
    D = rng.normal(size=(30, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    vis = trace(V, F, D)
    cos = V @ D.T
    assert vis.shape == (len(V), len(D))
    assert (vis[cos > 0.15] == 1).all() and (vis[cos < -0.15] == 0).all()


def test_cell_visibility_is_the_unblocked_share_of_each_lights_cell(mi):
    """On a sphere the unblocked share of a light's Voronoi cell is the share of the cell's directions in front
    of the vertex's tangent plane: 1 for a cell wholly in front, 0 wholly behind, in between for grazing."""
    from mifacerf.rendering.self_visibility import cell_directions, cell_visibility

    V, F = _sphere()
    rng = np.random.default_rng(1)
    D = rng.normal(size=(20, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    from mifacerf.rendering.self_visibility import trace

    vis = cell_visibility(V, F, D, n=2048)
    samples, cell = cell_directions(D, 2048)
    assert vis.shape == (len(V), len(D)) and ((vis >= 0) & (vis <= 1)).all()
    free = trace(V, F, samples)
    np.testing.assert_allclose(vis, np.stack([free[:, cell == l].mean(1) for l in range(len(D))], 1), atol=1e-6)
    cos = V @ samples.T                                            # (T, n): in front of the tangent plane > 0
    ahead = np.stack([(cos[:, cell == l] > 0.2).all(1) for l in range(len(D))], 1)
    behind = np.stack([(cos[:, cell == l] < -0.2).all(1) for l in range(len(D))], 1)
    assert ahead.any() and behind.any()
    assert (vis[ahead] == 1).all() and (vis[behind] == 0).all()
    grazing = ~ahead & ~behind
    front = np.stack([(cos[:, cell == l] > 0).mean(1) for l in range(len(D))], 1)
    assert ((vis[grazing] > 0) & (vis[grazing] < 1)).mean() > 0.5   # grazing cells are partly seen ...
    assert np.corrcoef(vis[grazing], front[grazing])[0, 1] > 0.9    # ... as much as they lie in front


def test_material_self_visibility_is_a_parameter(toy_model, mi):
    """facerf_bsdf's self_visibility (default on) reaches the material; off keeps the captured field as is."""
    from mifacerf.variant import ensure_plugins

    ensure_plugins()
    for flag in (True, False):
        scene = mi.load_dict({"type": "scene", "face": {"type": "facerf_face", "model": str(toy_model.root),
                                                        "bsdf": {"type": "facerf_bsdf", "self_visibility": flag}}})
        bsdf = scene.shapes()[0].bsdf()
        assert bsdf.state.self_visibility is flag
    # the rule: the one ray towards each light (0/1) or the unblocked share of its cell
    from mifacerf.rendering.self_visibility import visibility

    ray, cell = visibility(toy_model, "ray"), visibility(toy_model, "cell")
    assert set(np.unique(ray)) <= {0.0, 1.0} and ray.shape == cell.shape
    assert ((cell > 0) & (cell < 1)).any() and np.abs(ray - cell).mean() < 0.2


def test_material_renders_compressed_fields_by_method_name(toy_model, mi, tmp_path):
    """facerf_bsdf method='pca', rank=R reads the pca<R> files (mifacerf compress) and renders close to the
    exact fields; an unknown method lists the choices; pca without its files names the missing file."""
    import shutil

    import pytest

    from mifacerf.camera import Camera
    from mifacerf.rendering.compression import compress_model
    from mifacerf.rendering.model import Model
    from mifacerf.rendering.sensors import sensor_dict
    from mifacerf.variant import ensure_plugins

    ensure_plugins()
    root = tmp_path / "model"
    shutil.copytree(toy_model.root, root)
    compress_model(Model(root), 8, progress=False, method="pca")
    cam = Camera.look_at("t", [0.12, 0.1, 1.0], [0, 0, 0], width=24, height=24, focal=96.0)

    def render(**bsdf):
        scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                              "sensor": sensor_dict(cam, spp=16), "light": {"type": "directional",
                                                                             "direction": [0, 0, -1]},
                              "face": {"type": "facerf_face", "model": str(root),
                                       "bsdf": {"type": "facerf_bsdf", **bsdf}}})
        return np.asarray(mi.render(scene, seed=0))[..., :3]

    exact, pca = render(), render(method="pca", rank=8)
    assert exact.max() > 0
    err = np.sqrt(((exact - pca) ** 2).mean())
    assert err < 0.05 * exact.max(), err
    # sh (spherical-harmonic fields, reconstructed per light's cell at upload) by its name too
    compress_model(Model(root), 8, progress=False, method="sh")
    sh = render(method="sh", rank=8)
    assert np.isfinite(sh).all() and np.sqrt(((exact - sh) ** 2).mean()) < 0.25 * exact.max()
    with pytest.raises(Exception, match="unknown compression method 'zip'; choose one of exact, pca"):
        render(method="zip")
    with pytest.raises(Exception, match="pca3"):
        render(method="pca", rank=3)
    # a scene that failed at load leaves its BSDF registered; later scenes still render (Dr.Jit traces it too)
    np.testing.assert_allclose(render(), exact, atol=1e-6)


def test_mifacerf_evaluate_material_prints_the_table(toy_model):
    """'mifacerf evaluate material MODEL' runs the comparison (tiny here) and prints its table."""
    from click.testing import CliRunner

    from mifacerf.evaluation.cli import evaluate_group

    r = CliRunner().invoke(evaluate_group, ["material", str(toy_model.root), "--env", "sky", "--size", "16",
                                            "--spp", "4", "--integrators", "direct"])
    assert r.exit_code == 0, r.output
    assert "| direct | 2 x 4 |" in r.output and "facerf (exact)" in r.output
    # the material's options and the view, as python -m mifacerf.evaluation.material takes them
    r = CliRunner().invoke(evaluate_group, ["material", str(toy_model.root), "--env", "sky", "--size", "16",
                                            "--spp", "4", "--integrators", "direct", "--eye", "0.5,0.1,0.9",
                                            "--visibility-grid", "1", "--visibility-emitter"])
    assert r.exit_code == 0, r.output
    assert "| direct | 2 x 4 |" in r.output
    r = CliRunner().invoke(evaluate_group, ["material", str(toy_model.root), "--eye", "1,2"])
    assert r.exit_code == 2 and "'--eye': expected three finite numbers X,Y,Z" in r.output, r.output
    assert "Traceback" not in r.output


def test_triangle_visibility_follows_each_triangles_plane(mi):
    """Inside each triangle of a sphere (the grid of points traced from its surface, as shadow rays are), a light
    is seen iff it lies in front of the triangle's plane (away from grazing); rows with i + j > order hold 1."""
    from mifacerf.rendering.self_visibility import grid_barycentrics, triangle_visibility

    V, F = _sphere(200)
    rng = np.random.default_rng(2)
    D = rng.normal(size=(12, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    vis = triangle_visibility(V, F, D, rule="ray", order=2)
    B = grid_barycentrics(2)
    assert vis.shape == (len(F), 9, len(D)) and B.shape == (9, 3)
    np.testing.assert_allclose(B.sum(1), 1.0)
    ij = np.array([(i, j) for i in range(3) for j in range(3)])
    valid = ij.sum(1) <= 2
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cos = np.repeat((n @ D.T)[:, None], valid.sum(), 1)
    v = vis[:, valid]
    assert (v[cos > 0.15] == 1).all() and (v[cos < -0.05] == 0).all()
    assert (vis[:, ~valid] == 1).all()
    cell = triangle_visibility(V, F, D, rule="cell", order=1, n=1024)
    assert ((cell >= 0) & (cell <= 1)).all()


def test_the_grid_interpolation_lands_on_its_points(mi):
    """MaterialState's lookup of the grid (corners and weights at barycentrics b) gives weight 1 to the grid point
    at b, and weights that sum to 1 and reproduce b linearly in between."""
    import types

    from mifacerf.rendering.material import MaterialState
    from mifacerf.rendering.self_visibility import grid_barycentrics

    k = 3
    stub = types.SimpleNamespace(mi=mi, visibility_grid=k)
    B = grid_barycentrics(k)
    ij = np.array([(i, j) for i in range(k + 1) for j in range(k + 1)])
    valid = np.flatnonzero(ij.sum(1) <= k)
    rng = np.random.default_rng(3)
    mid = rng.dirichlet([1, 1, 1], 50)
    b = np.concatenate([B[valid], mid])
    corners, weights = MaterialState._grid_corners(stub, [mi.Float(b[:, 0]), mi.Float(b[:, 1]), mi.Float(b[:, 2])])
    c = np.stack([np.asarray(x) for x in corners], 1)
    w = np.stack([np.asarray(x) for x in weights], 1)
    np.testing.assert_allclose(w.sum(1), 1.0, atol=1e-5)
    assert (ij[c].sum(-1) <= k).all()                              # only points of the grid
    n = len(valid)
    picked = np.take_along_axis(c, np.argmax(w, 1)[:, None], 1)[:n, 0]
    np.testing.assert_array_equal(picked, valid)
    np.testing.assert_allclose(w[:n].max(1), 1.0, atol=1e-4)
    inside = mid.min(1) > 0.06                                    # inside the inset grid: linear reproduction
    rec = np.einsum("nc,ncd->nd", w[n:], B[c[n:]])
    np.testing.assert_allclose(rec[inside], mid[inside], atol=1e-4)


def test_the_grids_are_kept_on_disk_by_what_they_are_computed_from(mi, tmp_path, monkeypatch):
    """A second process reads a source's grid from the user's cache (the same array to the bit) instead of
    tracing it again; other vertices or another rule are another file; a damaged file is named and recomputed;
    MIFACERF_VISIBILITY_CACHE=0 writes nothing."""
    import warnings

    import pytest

    from mifacerf.rendering import self_visibility as sv

    monkeypatch.setenv("MIFACERF_CACHE", str(tmp_path))
    monkeypatch.delenv("MIFACERF_VISIBILITY_CACHE", raising=False)
    V, F = _sphere(120)
    D = np.random.default_rng(3).normal(size=(8, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    traced = []
    real = sv.triangle_visibility
    monkeypatch.setattr(sv, "triangle_visibility", lambda *a, **k: traced.append(1) or real(*a, **k))
    first = sv.cached_triangle_visibility(V, F, D, rule="ray", order=2)
    again = sv.cached_triangle_visibility(V, F, D, rule="ray", order=2)
    assert len(traced) == 1 and again.dtype == np.float32 and np.array_equal(first, again)
    assert np.array_equal(first, real(V, F, D, rule="ray", order=2))
    files = sorted((tmp_path / "visibility").glob("grid-*.npy"))
    assert len(files) == 1
    moved = V * 1.01
    sv.cached_triangle_visibility(moved, F, D, rule="ray", order=2)
    sv.cached_triangle_visibility(V, F, D, rule="ray", order=1)
    assert len(traced) == 3 and len(list((tmp_path / "visibility").glob("grid-*.npy"))) == 3
    files[0].write_bytes(b"not an array")
    with pytest.warns(UserWarning, match=rf"{files[0].name}: a damaged self-visibility cache file"):
        fixed = sv.cached_triangle_visibility(V, F, D, rule="ray", order=2)
    assert len(traced) == 4 and np.array_equal(fixed, first)
    np.save(files[0], np.full(first.shape, 2.0, np.float32))          # out of [0, 1]
    with pytest.warns(UserWarning, match="recomputed"):
        assert np.array_equal(sv.cached_triangle_visibility(V, F, D, rule="ray", order=2), first)
    monkeypatch.setenv("MIFACERF_VISIBILITY_CACHE", "0")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sv.cached_triangle_visibility(V * 1.02, F, D, rule="ray", order=2)
    assert len(traced) == 6 and len(list((tmp_path / "visibility").glob("grid-*.npy"))) == 3


def test_the_disk_cache_keeps_the_most_recently_used_grids(tmp_path):
    """trim_cache deletes the least recently used files (a read renews a file's time) down to the bound, and
    never the newest."""
    import os

    from mifacerf.rendering.self_visibility import trim_cache

    for i in range(5):
        p = tmp_path / f"grid-{i}.npy"
        p.write_bytes(b"x" * 400_000)
        os.utime(p, ns=(10 ** 18 + i * 10 ** 9,) * 2)   # grid-4 the newest
    os.utime(tmp_path / "grid-0.npy")                  # read just now: the most recent of all
    (tmp_path / "other.txt").write_bytes(b"y" * 10 ** 6)
    gone = trim_cache(tmp_path, limit_mb=1.0)
    assert sorted(p.name for p in gone) == ["grid-1.npy", "grid-2.npy", "grid-3.npy"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["grid-0.npy", "grid-4.npy", "other.txt"]
    assert trim_cache(tmp_path, limit_mb=0.0) == [tmp_path / "grid-4.npy"]   # the newest (grid-0) stays


def test_a_bad_cache_bound_is_named(tmp_path, monkeypatch):
    import pytest

    from mifacerf.rendering.self_visibility import trim_cache

    (tmp_path / "grid-0.npy").write_bytes(b"x")
    monkeypatch.setenv("MIFACERF_VISIBILITY_CACHE_MB", "lots")
    with pytest.warns(UserWarning, match="MIFACERF_VISIBILITY_CACHE_MB='lots' is not a size"):
        assert trim_cache(tmp_path) == []


def test_on_the_phong_surface_the_grid_lies_on_the_scene_skin_and_faces_its_sub_faces(mi):
    """``curved`` > 1: each grid point lies on the Phong surface the scene traces — a ray cast down onto it from
    1 mm out (Mitsuba's own intersection with the tessellated mesh) meets it there, on a sub-face whose map back to
    the template triangle (``PhongTessellation.to_coarse``) gives the grid point's own triangle and barycentrics —,
    and a light is seen iff it lies in front of the plane of the sub-face Mitsuba reports (away from grazing). The
    flat rule answers otherwise for some of them (the template's facets are tilted against the sub-faces)."""
    from mifacerf.geometry.boubekeur2008 import PhongTessellation
    from mifacerf.jitarrays import to_jit
    from mifacerf.rendering.self_visibility import _on_phong_surface, grid_barycentrics, triangle_visibility

    V, F = _sphere(40)
    level, order = 3, 2          # order 2's inset points lie inside level 3's sub-faces, not on their edges
    rng = np.random.default_rng(7)
    D = rng.normal(size=(24, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    vis = triangle_visibility(V, F, D, rule="ray", order=order, curved=level)
    flat = triangle_visibility(V, F, D, rule="ray", order=order)
    B = grid_barycentrics(order)
    ij = np.array([(i, j) for i in range(order + 1) for j in range(order + 1)])
    valid = ij.sum(1) <= order
    G = int(valid.sum())
    assert vis.shape == flat.shape == (len(F), len(B), len(D)) and (vis[:, ~valid] == 1).all()

    t = PhongTessellation(F, len(V), level)
    Vs = t.positions(V)
    mesh = mi.Mesh("phong", len(Vs), len(t.faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = to_jit(mi.Float, Vs.reshape(-1).astype(np.float32))
    params["faces"] = to_jit(mi.UInt32, t.faces.reshape(-1).astype(np.uint32))
    params.update()
    scene = mi.load_dict({"type": "scene", "mesh": mesh})
    _, _, P, N = _on_phong_surface(V, F, B[valid], level)
    P, N = P.reshape(-1, 3), N.reshape(-1, 3)
    assert (np.einsum("nd,nd->n", N, P) > 0).all()                       # outward
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f((P + 1e-3 * N).T.astype(np.float32)),
                                      mi.Vector3f((-N).T.astype(np.float32))))
    assert np.asarray(si.is_valid()).all()
    np.testing.assert_allclose(np.asarray(si.t), 1e-3, atol=2e-6)
    hit, n = np.asarray(si.p).T, np.asarray(si.n).T
    np.testing.assert_allclose(np.einsum("nd,nd->n", n, N), 1.0, atol=1e-5)
    sub = np.asarray(si.prim_index, np.int64)
    tri = Vs[t.faces[sub]]                                               # (N, 3 corners, 3)
    A = np.stack([tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]], -1)
    w = np.stack([np.linalg.lstsq(A[k], hit[k] - tri[k, 0], rcond=None)[0] for k in range(len(hit))])
    coarse, cb = t.to_coarse(sub, np.stack([1 - w.sum(1), w[:, 0], w[:, 1]], 1))
    np.testing.assert_array_equal(coarse, np.repeat(np.arange(len(F)), G))
    np.testing.assert_allclose(cb, np.tile(B[valid], (len(F), 1)), atol=1e-4)
    cos = (n @ D.T).reshape(len(F), G, len(D))
    v = vis[:, valid]
    assert (v[cos > 0.15] == 1).all() and (v[cos < -0.05] == 0).all()
    assert (flat[:, valid] != v).any()


def test_cell_shares_weighted_by_the_environment_count_only_its_lit_directions(mi):
    """With per-sample weights (the environment's radiance along the cell samples), a light's share is the
    weighted share of its cell's free samples: on a sphere, 1 where every lit sample of the cell lies in front
    of the triangle's plane although the cell as a whole reaches behind it, 0 where every lit one lies behind;
    a cell with no lit sample keeps the unweighted share; uniform weights change nothing."""
    import pytest

    from mifacerf.rendering.self_visibility import cell_directions, triangle_visibility

    V, F = _sphere(200)
    rng = np.random.default_rng(3)
    D = rng.normal(size=(12, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    n = 1024
    samples, cell = cell_directions(D, n)
    plain = triangle_visibility(V, F, D, rule="cell", order=1, n=n)
    np.testing.assert_allclose(triangle_visibility(V, F, D, rule="cell", order=1, n=n, weights=np.full(n, 2.5)),
                               plain, atol=1e-5)
    w = np.where(samples[:, 2] > 0.3, 1.0 + rng.random(n), 0.0)        # light from the top cap only
    lit = triangle_visibility(V, F, D, rule="cell", order=1, n=n, weights=w)
    assert lit.shape == plain.shape and ((lit >= 0) & (lit <= 1)).all()
    nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    cos = nrm @ samples.T                                              # (F, n)
    valid = np.array([i + j <= 1 for i in range(2) for j in range(2)])
    n_front = n_behind = 0
    for l in range(len(D)):
        on = (cell == l) & (w > 0)
        if not on.any():                                               # no light in the cell: unweighted
            np.testing.assert_array_equal(lit[:, valid, l], plain[:, valid, l])
            continue
        front = (cos[:, on] > 0.1).all(1) & (cos[:, cell == l] < -0.1).any(1)
        behind = (cos[:, on] < -0.1).all(1) & (cos[:, cell == l] > 0.1).any(1)
        assert (lit[front][:, valid, l] == 1).all() and (plain[front][:, valid, l] < 1).all()
        assert (lit[behind][:, valid, l] == 0).all() and (plain[behind][:, valid, l] > 0).all()
        n_front, n_behind = n_front + front.sum(), n_behind + behind.sum()
    assert n_front > 0 and n_behind > 0                                # the test saw both kinds of cell
    for bad, words in ((np.ones(n - 1), "shape"), (-np.ones(n), ">= 0"), (np.zeros(n), "not all 0")):
        with pytest.raises(ValueError, match=words):
            triangle_visibility(V, F, D, rule="cell", order=1, n=n, weights=bad)
    with pytest.raises(ValueError, match="'cell' rule"):
        triangle_visibility(V, F, D, rule="ray", order=1, n=n, weights=w)


def test_the_material_weighs_its_visibility_by_the_referenced_environment(toy_model, mi):
    """facerf_bsdf visibility_emitter (a reference to the scene's environment) gives the material the
    environment's luminance along the cell samples; a constant environment weighs them all alike, so the
    grids are the unweighted ones; a point light or a non-emitter is one error naming the parameter."""
    import pytest

    from mifacerf.rendering.self_visibility import CELL_SAMPLES
    from mifacerf.variant import ensure_plugins

    ensure_plugins()

    def scene(emitter, ref=True):
        bsdf = {"type": "facerf_bsdf", "visibility_grid": 1}
        if ref:
            bsdf["visibility_emitter"] = {"type": "ref", "id": "env"}
        return mi.load_dict({"type": "scene", "env": emitter,
                             "face": {"type": "facerf_face", "model": str(toy_model.root), "bsdf": bsdf}})

    const = {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 1.0, 2.0]}}
    state = scene(const).shapes()[0].bsdf().state
    w = state.visibility_weights
    assert w.shape == (CELL_SAMPLES,)
    np.testing.assert_allclose(w, 0.2126 * 0.5 + 0.7152 * 1.0 + 0.0722 * 2.0, rtol=1e-5)
    plain = scene(const, ref=False).shapes()[0].bsdf().state
    assert plain.visibility_weights is None
    np.testing.assert_allclose(np.asarray(state.vis_grid), np.asarray(plain.vis_grid), atol=1e-5)
    # the scene-file form the manual gives: <ref name="visibility_emitter" id="..."/>
    xml = mi.load_string(f"""<scene version="3.0.0">
        <emitter type="constant" id="env"><rgb name="radiance" value="0.5, 1.0, 2.0"/></emitter>
        <shape type="facerf_face"><string name="model" value="{toy_model.root}"/>
            <bsdf type="facerf_bsdf"><integer name="visibility_grid" value="1"/>
                <ref name="visibility_emitter" id="env"/></bsdf></shape></scene>""")
    np.testing.assert_allclose(xml.shapes()[0].bsdf().state.visibility_weights, w)
    with pytest.raises(Exception, match="visibility_emitter.*environment.*got PointLight"):
        scene({"type": "point", "position": [0, 0, 2], "intensity": {"type": "rgb", "value": 1.0}})
