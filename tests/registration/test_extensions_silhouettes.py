"""Extensions fitted to the capture's outlines (issue 16): a template extension placed with clicking error
moves along its normals until its outline in every camera lies on the subject's."""
import numpy as np
import pytest

from mifacerf.camera import Camera
from mifacerf.geometry.meshscene import MeshScene
from mifacerf.registration.extensions import mesh_matte, outline_offsets, refine_to_silhouettes, silhouette_matte
from mifacerf.geometry.visibility import vertex_normals


def _sphere(n_lat=14, n_lon=24, r=0.1):
    V = [[0, r, 0]]
    for i in range(1, n_lat):
        th = np.pi * i / n_lat
        for j in range(n_lon):
            ph = 2 * np.pi * j / n_lon
            V.append([r * np.sin(th) * np.cos(ph), r * np.cos(th), r * np.sin(th) * np.sin(ph)])
    V.append([0, -r, 0])
    V = np.array(V)
    F, last = [], len(V) - 1
    ring = lambda i, j: 1 + (i - 1) * n_lon + j % n_lon  # noqa: E731
    for j in range(n_lon):
        F.append([0, ring(1, j + 1), ring(1, j)])
        F.append([last, ring(n_lat - 1, j), ring(n_lat - 1, j + 1)])
    for i in range(1, n_lat - 1):
        for j in range(n_lon):
            a, b, c, d = ring(i, j), ring(i, j + 1), ring(i + 1, j), ring(i + 1, j + 1)
            F += [[a, b, c], [b, d, c]]
    return V, np.array(F)


def _cameras(n=4, size=64):
    cams = []
    for k in range(n):
        a = 2 * np.pi * k / n + 0.3
        cams.append(Camera.look_at(f"c{k}", [0.8 * np.sin(a), 0.1, 0.8 * np.cos(a)], [0, 0, 0], width=size,
                                   height=size, focal=220.0))
    return cams


def test_silhouette_matte_is_the_coverage_of_an_evenly_lit_subject():
    img = np.zeros((9, 9, 3))
    img[2:7, 2:7] = 0.6
    img[2:7, 7] = 0.3                                  # a column half covered
    a = silhouette_matte(img)
    assert (a[3:6, 3:6] == 1).all() and (a[0] == 0).all()
    np.testing.assert_allclose(a[3:6, 7], 0.5)


def test_refinement_brings_a_noisy_extension_onto_the_subjects_outline():
    V, F = _sphere()
    fine_V, fine_F = _sphere(40, 64)
    cams = _cameras()
    truth = MeshScene(fine_V, fine_F)
    mattes = [mesh_matte(truth, c, spp=16) for c in cams]
    rng = np.random.default_rng(3)
    ids = np.flatnonzero(V[:, 1] > -0.05)             # the "extension": everything above a cut
    noisy = V.copy()
    N = vertex_normals(V, F)
    noisy[ids] += rng.normal(0, 0.002, len(ids))[:, None] * N[ids]

    def outline_error(X):
        scene, N = MeshScene(X, F), vertex_normals(X, F)
        offs = [outline_offsets(X, N, ids, c, m, mesh_matte(scene, c)) for c, m in zip(cams, mattes)]
        o = np.concatenate([x[0] for x in offs])
        w = np.concatenate([x[1] for x in offs])
        return np.abs(o[w > 0]).mean()

    before = outline_error(noisy)
    fitted, rep = refine_to_silhouettes(noisy, F, ids, cams, mattes)
    after = outline_error(fitted)
    assert before > 1e-3 and after < 0.5 * before, (before, after)
    assert rep["rounds"] and rep["rounds"][0]["measured"] > 10
    fixed = np.setdiff1d(np.arange(len(V)), ids)
    assert (fitted[fixed] == noisy[fixed]).all()      # the rest of the mesh (the face) stays where it is


def test_fitting_against_the_phong_surface_keeps_vertices_on_the_subject():
    """The fit measures the outline of the surface the renders trace (``curved``): against the flat chords it
    pushes outline vertices out by part of the sag (the flat outline lies inside a round subject), against
    the Phong surface they stay on the sphere, and that surface then covers the subject's matte far better
    than the flat fit's chords do."""
    from mifacerf.geometry.meshscene import CurvedMeshScene

    V, F = _sphere(8, 12)                              # coarse: chords sag ~3 mm at the equator
    fine_V, fine_F = _sphere(40, 64)
    cams = _cameras()
    mattes = [mesh_matte(MeshScene(fine_V, fine_F), c, spp=16) for c in cams]
    ids = np.flatnonzero(V[:, 1] > -0.05)

    def fit(level):
        X, _ = refine_to_silhouettes(V, F, ids, cams, mattes, curved=level)
        scene = MeshScene(X, F) if level == 1 else CurvedMeshScene(X, F, level)
        err = np.mean([np.abs(mesh_matte(scene, c, spp=16) - m).sum() for c, m in zip(cams, mattes)])
        return np.abs(np.linalg.norm(X[ids], axis=1) - 0.1).mean(), err

    off_flat, err_flat = fit(1)
    off_curved, err_curved = fit(3)
    assert off_curved < 0.5 * off_flat, (off_curved, off_flat)
    assert err_curved < 0.3 * err_flat, (err_curved, err_flat)
    with pytest.raises(ValueError, match="curved must be a whole number"):
        refine_to_silhouettes(V, F, ids, cams, mattes, curved=0)


def test_a_second_pose_constrains_vertices_the_first_poses_outlines_miss():
    """``poses``: the same vertices seen in another (rigid) pose share one displacement along the normals, so
    outlines of the turned mesh fit vertices the first pose's cameras never see on an outline; the moved
    poses stay one rigid motion apart."""
    V, F = _sphere()
    fine_V, fine_F = _sphere(40, 64)
    cams = _cameras()
    a = np.radians(70)
    R = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])   # tipped about x
    truth0 = MeshScene(fine_V, fine_F)
    truth1 = MeshScene(fine_V @ R.T, fine_F)
    mattes0 = [mesh_matte(truth0, c, spp=16) for c in cams]
    mattes1 = [mesh_matte(truth1, c, spp=16) for c in cams]
    rng = np.random.default_rng(5)
    ids = np.arange(len(V))
    N = vertex_normals(V, F)
    noisy = V + rng.normal(0, 0.002, len(V))[:, None] * N
    one, rep1 = refine_to_silhouettes(noisy, F, ids, cams, mattes0)
    two, rep2 = refine_to_silhouettes(noisy, F, ids, cams, mattes0, poses=[(noisy @ R.T, cams, mattes1, None)])
    assert rep2["rounds"][0]["measured"] > 1.3 * rep1["rounds"][0]["measured"]
    np.testing.assert_allclose(rep2["moved_poses"][0], two @ R.T, atol=1e-9)
    err = lambda X: np.abs(np.linalg.norm(X, axis=1) - 0.1)   # noqa: E731  (the sphere's radius: the truth)
    top = np.abs(V[:, 1]) > 0.07                  # near the poles: on no outline of the level cameras
    assert err(two)[top].mean() < 0.85 * err(one)[top].mean(), (err(two)[top].mean(), err(one)[top].mean())
    assert err(two).mean() < err(one).mean()
    with pytest.raises(ValueError, match="every pose needs"):
        refine_to_silhouettes(noisy, F, ids, cams, mattes0, poses=[(noisy[:-1], cams, mattes1, None)])
