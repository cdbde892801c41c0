"""Primary hits by rasterisation (:mod:`mifacerf.geometry.raster`) against Mitsuba's own ray cast
(``ray_intersect_preliminary`` through :meth:`MeshScene.trace`, culled): the same triangles, barycentrics
and distances, flat and on the Phong surface, with lens distortion; the fall-backs."""
import numpy as np
import pytest

pytest.importorskip("numba")

from mifacerf.camera import Camera  # noqa: E402
from mifacerf.geometry import raster  # noqa: E402


def _scene_mesh():
    """Two overlapping ellipsoids (closed: back faces behind front ones), an open cup whose inside faces the
    camera through its rim (back faces seen first, then its front faces from inside), a triangle facing
    away: every case of the culled trace."""
    import trimesh

    a = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    b = trimesh.creation.icosphere(subdivisions=2, radius=0.06)
    av = a.vertices * [1.0, 1.3, 0.9]
    bv = b.vertices + [0.07, -0.02, 0.06]
    cup = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    keep = cup.vertices[cup.faces].mean(1)[:, 2] < 0.0          # the far half: open towards the camera
    cv = cup.vertices + [-0.12, 0.09, 0.05]
    away = np.array([[0.1, 0.12, 0.12], [0.16, 0.12, 0.12], [0.1, 0.18, 0.12]])   # normal towards -z: away
    V = np.concatenate([av, bv, cv, away])
    F = np.concatenate([a.faces, b.faces + len(av), cup.faces[keep] + len(av) + len(bv),
                        np.array([[0, 2, 1]]) + len(av) + len(bv) + len(cv)])
    return V, F


def _camera(dist=None):
    return Camera.look_at("c", [0.05, 0.03, 0.6], [0, 0, 0], width=96, height=80, focal=160.0,
                          principal_offset=(1.5, -2.0), dist=dist)


def _compare(hits, ref):
    assert (hits.valid != ref.valid).mean() < 2e-4          # an edge case or two of float32 against float64
    both = hits.valid & ref.valid
    assert both.sum() > 0.3 * len(both)
    assert (hits.tri[both] == ref.tri[both]).mean() > 0.999
    same = both & (hits.tri == ref.tri)
    assert np.quantile(np.abs(hits.bary[same] - ref.bary[same]).max(1), 0.999) < 1e-4
    np.testing.assert_allclose(hits.t[same], ref.t[same], rtol=1e-5)
    assert np.isinf(hits.t[~hits.valid]).all() and (hits.tri[~hits.valid] == -1).all()


@pytest.mark.parametrize("curved", [1, 3])
@pytest.mark.parametrize("dist", [None, (-0.2, 0.05, 0.001, -0.002, 0.0)])
def test_camera_hits_are_mitsubas(mi, curved, dist):
    from mifacerf.camera import stratified_pixel_samples
    from mifacerf.geometry.meshscene import CurvedMeshScene, MeshScene

    V, F = _scene_mesh()
    scene = MeshScene(V, F) if curved == 1 else CurvedMeshScene(V, F, curved)
    cam = _camera(dist)
    uv = stratified_pixel_samples(cam.width, cam.height, 4, 3)
    xn = cam.undistort_pixels(uv)
    grid = raster.SampleGrid(xn, cam.width, cam.height)
    o, d = cam.pixel_rays(uv)
    hits = scene.camera_hits(cam, grid, d)
    ref = scene.trace(o, d, cull_back=True)
    _compare(hits, ref)
    if curved > 1:
        assert hits.sub is not None and (hits.sub[hits.valid] >= 0).all()
        both = hits.valid & ref.valid
        assert (hits.sub[both] == ref.sub[both]).mean() > 0.999
    # moved lazily: the raster sees the new vertices at once, Mitsuba's scene when next used
    scene.set_vertices(V + [0.01, 0.0, 0.0], lazy=True)
    _compare(scene.camera_hits(cam, grid, d), scene.trace(o, d, cull_back=True))


def test_culling_and_what_lies_behind_the_camera(mi):
    from mifacerf.geometry.meshscene import MeshScene

    cam = Camera.look_at("c", [0, 0, 1.0], [0, 0, 0], width=20, height=20, focal=40.0)
    plane = cam.undistort_pixels(np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2))
    grid = raster.SampleGrid(plane, 20, 20)
    tri = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]])   # the camera looks along -z
    front, back = np.array([[0, 1, 2]]), np.array([[0, 2, 1]])
    n_front = (raster.camera_hits(tri, front, cam.centre, cam.R, grid)[0] >= 0).sum()
    assert n_front > 100
    assert (raster.camera_hits(tri, back, cam.centre, cam.R, grid)[0] < 0).all()            # culled
    assert (raster.camera_hits(tri, back, cam.centre, cam.R, grid, cull_back=False)[0] >= 0).sum() == n_front
    behind = tri + [0, 0, 2.0]                                                              # wholly behind
    V = np.concatenate([tri, behind])
    out = raster.camera_hits(V, np.array([[0, 1, 2], [3, 4, 5]]), cam.centre, cam.R, grid)
    assert out is not None and set(np.unique(out[0])) <= {-1, 0} and (out[0] == 0).sum() == n_front
    through = np.array([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [0.0, 0.0, 3.0]])                 # through the camera's plane
    assert raster.camera_hits(through, front, cam.centre, cam.R, grid) is None
    scene = MeshScene(np.concatenate([tri, through]), np.array([[0, 1, 2], [3, 4, 5]]))
    o, d = cam.pixel_rays(np.stack(np.meshgrid(np.arange(20.0), np.arange(20.0)), -1).reshape(-1, 2))
    hits = scene.camera_hits(cam, grid, d)             # ray-cast instead: the same answer as the trace
    ref = scene.trace(o, d, cull_back=True)
    np.testing.assert_array_equal(hits.tri, ref.tri)


def test_switched_off_and_bad_planes(monkeypatch):
    monkeypatch.setenv("MIFACERF_NUMBA_RASTER", "0")
    assert not raster.available()
    monkeypatch.delenv("MIFACERF_NUMBA_RASTER")
    assert raster.available()
    with pytest.raises(ValueError, match=r"sample plane of shape \(4, 3\)"):
        raster.SampleGrid(np.zeros((4, 3)), 2, 2)
    with pytest.raises(ValueError, match="NaN"):
        raster.SampleGrid(np.array([[0.0, np.nan]]), 2, 2)


def test_an_unchanged_mesh_is_not_rebuilt(mi):
    """Mitsuba rebuilds the BVH on every update: an update with the vertices its scene already holds is
    skipped (counted on the scene's parameter updates), a changed one is not, and rays see the change."""
    from mifacerf.geometry.meshscene import MeshScene

    V, F = _scene_mesh()
    scene = MeshScene(V, F)
    before = scene.trace(np.array([0.0, 0.0, 1.0]), np.array([[0.0, 0.0, -1.0]]))
    calls = []
    params = scene._scene_params
    real = params.update
    params.update = lambda *a, **k: (calls.append(1), real(*a, **k))[1]
    scene.set_vertices(V.copy())
    scene.set_vertices(V.copy(), lazy=True)
    scene.commit()
    assert calls == []
    moved = V + [0.0, 0.0, 0.05]
    scene.set_vertices(moved)
    assert calls == [1]
    hit = scene.trace(np.array([0.0, 0.0, 1.0]), np.array([[0.0, 0.0, -1.0]]))
    assert hit.valid[0] and np.isclose(hit.t[0], before.t[0] - 0.05, atol=1e-5)
    scene.set_vertices(moved, lazy=True)           # pending but unchanged: nothing to rebuild either
    scene.trace(np.array([0.0, 0.0, 1.0]), np.array([[0.0, 0.0, -1.0]]))
    assert calls == [1]
