"""Phong tessellation (geometry.boubekeur2008) and the curved mesh scene: identity at level 1, exact
barycentric maps, a watertight split, the sphere's analytic surface approached, degenerate input."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from mifacerf.geometry.boubekeur2008 import PhongTessellation


def icosphere(subdivisions=1):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def test_level_one_is_the_coarse_mesh():
    V, F = icosphere(1)
    t = PhongTessellation(F, len(V), level=1)
    assert np.array_equal(t.faces, F) and t.n_sub == len(V)
    assert np.allclose(t.positions(V), V)
    tri, bary = t.to_coarse(np.array([3, -1]), np.array([[0.2, 0.3, 0.5], [0, 0, 0]]))
    assert tri.tolist() == [3, -1] and np.allclose(bary[0], [0.2, 0.3, 0.5]) and np.all(bary[1] == 0)


@pytest.mark.parametrize("level", [2, 3, 4])
def test_split_is_watertight_and_maps_back_exactly(level):
    V, F = icosphere(1)
    t = PhongTessellation(F, len(V), level=level, alpha=0.0)   # alpha 0: the flat triangles, split
    assert len(t.faces) == level ** 2 * len(F)
    # closed: every sub-edge in exactly two sub-faces; Euler characteristic of a sphere
    e = np.sort(np.concatenate([t.faces[:, [0, 1]], t.faces[:, [1, 2]], t.faces[:, [2, 0]]]), axis=1)
    _, count = np.unique(e, axis=0, return_counts=True)
    assert (count == 2).all()
    assert t.n_sub - len(count) + len(t.faces) == 2
    # each sub-face's corners, mapped to the coarse face, are where the flat split put them
    P = t.positions(V)
    for k in (0, 1, 2):
        tri, bary = t.to_coarse(np.arange(len(t.faces)), np.eye(3)[np.full(len(t.faces), k)])
        assert np.allclose(np.einsum("nk,nkd->nd", bary, V[F[tri]]), P[t.faces[:, k]], atol=1e-12)
    # a point inside a sub-face maps to the same point of its coarse face
    rng = np.random.default_rng(0)
    b = rng.dirichlet(np.ones(3), len(t.faces))
    tri, bary = t.to_coarse(np.arange(len(t.faces)), b)
    assert np.allclose(bary.sum(1), 1) and (bary >= -1e-12).all()
    assert np.allclose(np.einsum("nk,nkd->nd", bary, V[F[tri]]), np.einsum("nk,nkd->nd", b, P[t.faces]), atol=1e-12)
    # the orientation of every sub-face is its coarse face's
    n_sub = np.cross(P[t.faces[:, 1]] - P[t.faces[:, 0]], P[t.faces[:, 2]] - P[t.faces[:, 0]])
    n_c = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])[t.parent]
    assert (np.einsum("nd,nd->n", n_sub, n_c) > 0).all()


def test_the_sphere_is_approached():
    """On a unit sphere with its exact normals, the Phong points (α = 1/2) lie far closer to the sphere than
    the chords' (the chord's sag is the flat error, all inside); the paper's α = 3/4 overshoots outwards by
    about half the sag (the midpoint rule of ALPHA's comment: radius 1 + (α − 1/2) θ²)."""
    V, F = icosphere(1)
    r = {a: np.linalg.norm(PhongTessellation(F, len(V), level=4, alpha=a).positions(V, N=V), axis=1)[len(V):] - 1
         for a in (0.0, 0.5, 0.75)}
    e_flat, e_curved = np.abs(r[0.0]).max(), np.abs(r[0.5]).max()
    assert e_flat > 0.05 and (r[0.0] < 0).all()    # 42 vertices: a coarse polygon, inside the sphere
    assert e_curved < 0.15 * e_flat
    assert 0.25 < r[0.75].mean() / -r[0.0].mean() < 0.6
    curved = PhongTessellation(F, len(V), level=4).positions(V, N=V)
    # the vertices themselves are interpolated
    assert np.allclose(curved[:len(V)], V)


def test_only_the_chosen_faces_are_split():
    V, F = icosphere(1)
    only = np.zeros(len(F), bool)
    only[:10] = True
    t = PhongTessellation(F, len(V), level=3, only=only)
    assert len(t.faces) == 10 * 9 + (len(F) - 10)
    flat_rows = ~only[t.parent]
    assert np.array_equal(t.faces[flat_rows], F[~only])


def test_a_part_curved_with_the_whole_surfaces_normals_has_the_whole_surfaces_sub_faces():
    """``normals_from``: curving a patch of a surface with the vertex normals of the whole gives each patch
    face the very sub-faces of the whole surface curved (a scene can curve only where it matters); with the
    patch's own normals (the default) the faces on the patch's rim bend otherwise."""
    V, F = icosphere(2)
    V = V * np.array([1.0, 0.8, 1.3])              # an ellipsoid: the normals are not the positions
    only = V[F].mean(1)[:, 2] > 0.6                 # a cap
    whole = PhongTessellation(F, len(V), level=3)
    patch = PhongTessellation(F, len(V), level=3, only=only, normals_from=np.ones(len(F), bool))
    own = PhongTessellation(F, len(V), level=3, only=only)

    def corners(t, P):
        # the sub-faces' corner points of each patch face, by the face and the corners' barycentrics
        rows = np.flatnonzero(only[t.parent])
        keys = list(t.corner_bary[rows].reshape(len(rows), -1).round(9).T[::-1]) + [t.parent[rows]]
        key = np.lexsort(keys)                      # by parent face first, then the corners' barycentrics
        return P[t.faces[rows[key]]]

    P_whole, P_patch, P_own = whole.positions(V), patch.positions(V), own.positions(V)
    np.testing.assert_allclose(corners(patch, P_patch), corners(whole, P_whole), atol=1e-12)
    assert np.abs(corners(own, P_own) - corners(whole, P_whole)).max() > 1e-3
    with pytest.raises(ValueError, match="normals_from has shape"):
        PhongTessellation(F, len(V), level=3, only=only, normals_from=np.ones(3, bool))


def test_bad_input_names_the_problem():
    V, F = icosphere(0)
    with pytest.raises(ValueError, match="level"):
        PhongTessellation(F, len(V), level=0)
    with pytest.raises(ValueError, match="out of range"):
        PhongTessellation(F, 3, level=2)
    t = PhongTessellation(F, len(V), level=2)
    with pytest.raises(ValueError, match=r"\(12, 3\)"):
        t.positions(V[:5])


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.sampled_from([2, 3]))
def test_degenerate_triangles_stay_finite(seed, level):
    """Collapsed triangles (all three vertices at one point, zero normals) give finite points on them."""
    rng = np.random.default_rng(seed)
    V, F = icosphere(0)
    V = V + 0.05 * rng.normal(size=V.shape)
    V[F[0]] = V[F[0, 0]]                 # one triangle collapsed to a point
    P = PhongTessellation(F, len(V), level=level).positions(V)
    assert np.isfinite(P).all()


def test_curved_scene_hits_the_curved_surface_and_reports_coarse_hits(mi):
    from mifacerf.geometry.meshscene import CurvedMeshScene, MeshScene

    V, F = icosphere(1)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    origins = 3.0 * d                       # rays from outside straight at the centre
    flat = MeshScene(V, F).trace(origins, -d, cull_back=True)
    curved_scene = CurvedMeshScene(V, F, level=4)
    curved = curved_scene.trace(origins, -d, cull_back=True)
    assert flat.valid.all() and curved.valid.all()
    r_flat, r_curved = 3.0 - flat.t, 3.0 - curved.t
    assert np.abs(r_curved - 1).mean() < 0.3 * np.abs(r_flat - 1).mean()
    # the reported coarse triangle is the one the ray crosses, its barycentrics a point on it near the ray
    assert (curved.tri >= 0).all() and curved.tri.max() < len(F)
    p = np.einsum("nk,nkd->nd", curved.bary, V[F[curved.tri]])
    cos = np.einsum("nd,nd->n", p / np.linalg.norm(p, axis=1, keepdims=True), d)
    assert cos.min() > 0.995
    assert (curved.tri == flat.tri).mean() > 0.97   # the same coarse face but where two meet at an edge
    # moving the coarse vertices moves the traced surface
    curved_scene.set_vertices(2 * V)
    again = curved_scene.trace(origins, -d, cull_back=True)
    assert np.allclose(3.0 - again.t, 2 * r_curved, atol=1e-4)
    assert np.array_equal(curved_scene.face_normals().shape, (len(F), 3))


def test_curved_scene_maps_hits_to_the_coarse_mesh_on_the_device_as_the_tessellation_does(mi):
    """CurvedMeshScene maps sub-face hits to (coarse face, barycentrics) inside the ray cast's kernel: the same
    answer as PhongTessellation.to_coarse on the sub-mesh's own hits, for one origin and for many."""
    from mifacerf.geometry.meshscene import CurvedMeshScene

    V, F = icosphere(1)
    scene = CurvedMeshScene(V, F, level=3)
    rng = np.random.default_rng(4)
    d = rng.normal(size=(3000, 3)) * [0.2, 0.2, 1.0] + [0, 0, -1]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for o in (np.array([0.0, 0.0, 3.0]), rng.normal(0, 0.05, (3000, 3)) + [0, 0, 3.0]):
        got = scene._trace_once(o, d)
        sub = scene._curved._trace_once(o, d)
        tri, bary = scene.tessellation.to_coarse(sub.tri, sub.bary)
        assert got.valid.any() and (~got.valid).any()           # hits and misses both
        np.testing.assert_array_equal(got.valid, sub.valid)
        np.testing.assert_array_equal(got.tri, tri)
        np.testing.assert_allclose(got.bary, bary, atol=1e-6)
        np.testing.assert_array_equal(got.t, sub.t)
        assert (got.bary[~got.valid] == 0).all() and (got.tri[~got.valid] == -1).all()
    # with back faces culled (rays from inside the sphere meet only its inside: no hit; from outside, its
    # front): as the sub-mesh's own trace
    o = np.concatenate([rng.normal(0, 0.05, (1500, 3)), rng.normal(0, 0.05, (1500, 3)) + [0, 0, 3.0]])
    got = scene.trace(o, d, cull_back=True)
    sub = scene._curved.trace(o, d, cull_back=True)
    tri, bary = scene.tessellation.to_coarse(sub.tri, sub.bary)
    assert got.valid.any() and (~got.valid).any()
    np.testing.assert_array_equal(got.tri, tri)
    np.testing.assert_allclose(got.bary, bary, atol=1e-6)
    np.testing.assert_allclose(got.t, sub.t, rtol=1e-6)
