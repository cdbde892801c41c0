"""Skin textures: wrinkles follow compression, the normal map's tangent frame matches Mitsuba's."""
import numpy as np
import pytest

from mifacerf.synthetic import default_subject
from mifacerf.synthetic.textures import encode_normals, value_noise


@pytest.fixture(scope="module")
def subj():
    return default_subject()


def _texels_where(subj, fn):
    P = subj.tex.tex_pos
    return subj.tex.covered[fn(P)]


def test_no_wrinkles_at_neutral(subj):
    pose = subj.neutral
    assert all(float(np.abs(a).max()) == 0.0 for a in pose.wrinkles.values())
    np.testing.assert_array_equal(pose.textures.normal_map, subj.tex.normal_map)
    np.testing.assert_array_equal(pose.textures.albedo, subj.tex.albedo)
    # blinking / gazing / turning the head make no wrinkles either
    for kw in ({"head_yaw": 0.5, "head_roll": 0.2}, {"gaze_yaw": 0.4}):
        pose = subj.pose(subj.params(**kw))
        assert max(float(a.max()) for a in pose.wrinkles.values()) == 0.0, kw


def test_brow_raise_wrinkles_the_forehead_only(subj):
    pose = subj.pose(subj.params(brow_raise_L=1, brow_raise_R=1))
    w = pose.wrinkles
    assert w["forehead"].max() > 0.3
    for k in ("neck", "lip_lines", "nasolabial_L", "nasolabial_R"):
        assert w[k].max() == 0.0, k
    # where: on the forehead vertices
    V0 = subj.neutral_skin
    hot = w["forehead"] > 0.2
    assert V0[hot, 1].min() > 0.025 and np.abs(V0[hot, 0]).max() < 0.07
    # the normal map changes on the forehead, nowhere near the chin or neck
    nm0 = subj.tex.normal_map.reshape(-1, 3)
    nm1 = pose.textures.normal_map.reshape(-1, 3)
    diff = np.abs(nm1 - nm0).max(axis=1)
    fore = _texels_where(subj, lambda P: (P[:, 1] > 0.035) & (P[:, 1] < 0.07) & (np.abs(P[:, 0]) < 0.03) & (P[:, 2] > 0.05))
    low = _texels_where(subj, lambda P: P[:, 1] < -0.06)
    assert diff[fore].max() > 0.1                     # real slopes (≈ 0.2 tilt or more)
    assert np.mean(diff[fore] > 0.02) > 0.2           # over much of the forehead
    assert diff[low].max() == 0.0
    # cavities darken the albedo a little, only there
    a0 = subj.tex.albedo.reshape(-1, 3)
    a1 = pose.textures.albedo.reshape(-1, 3)
    assert (a0[fore] - a1[fore]).max() > 0.02 and np.all(a1 <= a0 + 1e-7)
    assert np.abs(a1[low] - a0[low]).max() == 0.0


def test_other_wrinkles_follow_their_expressions(subj):
    cases = {"frown": "glabella", "pucker": "lip_lines", "cheek_raise_L": "crows_feet_L", "smile_R": "nasolabial_R"}
    for ctrl, fam in cases.items():
        w = subj.pose(subj.params(**{ctrl: 1.0})).wrinkles
        assert w[fam].max() > 0.3, (ctrl, fam)
    # left-right: a left smile does not wrinkle the right nasolabial fold
    w = subj.pose(subj.params(smile_L=1.0)).wrinkles
    assert w["nasolabial_L"].max() > 0.3 and w["nasolabial_R"].max() == 0.0


def test_texture_shapes_and_ranges(subj):
    tex = subj.neutral.textures
    r = subj.texture_resolution
    assert tex.albedo.shape == (r, r, 3) and tex.albedo.dtype == np.float32
    assert tex.roughness.shape == (r, r) and tex.normal_map.shape == (r, r, 3)
    for a in (tex.albedo, tex.roughness, tex.normal_map):
        assert np.all(np.isfinite(a)) and a.min() >= 0 and a.max() <= 1
    n = tex.normal_map * 2 - 1
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-4)
    assert n[..., 2].min() > 0.5
    # lips redder than cheeks, hair darker than skin
    alb = tex.albedo.reshape(-1, 3)
    P = subj.tex.tex_pos
    cov = subj.tex.covered
    from mifacerf.synthetic.textures import hair_mask, vermilion_mask

    lips = cov[vermilion_mask(P) > 0.9]
    hair = cov[hair_mask(P) > 0.9]
    cheek = cov[(np.abs(P[:, 0] - 0.045) < 0.005) & (np.abs(P[:, 1] + 0.02) < 0.005) & (P[:, 2] > 0.05)]
    assert alb[lips, 0].mean() / alb[lips, 1].mean() > 1.5 * alb[cheek, 0].mean() / alb[cheek, 1].mean()
    assert alb[hair].mean() < 0.3 * alb[cheek].mean()
    rough = tex.roughness.reshape(-1)
    assert rough[cov].std() > 0.02                     # spatially varying


def test_encode_normals():
    n = encode_normals(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, -1.0]], np.float32)) * 2 - 1
    np.testing.assert_allclose(n[0], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(n[1], np.array([-1, 0, 1]) / np.sqrt(2), atol=1e-6)   # height rising along s
    np.testing.assert_allclose(n[2], np.array([0, 1, 1]) / np.sqrt(2), atol=1e-6)


def test_value_noise_gradient():
    P = np.random.default_rng(0).random((500, 3)) * 0.01
    v, g = value_noise(P, 0.002, 3, grad=True)
    eps = 1e-7
    num = np.stack([(value_noise(P + eps * e, 0.002, 3) - value_noise(P - eps * e, 0.002, 3)) / (2 * eps)
                    for e in np.eye(3)], 1)
    np.testing.assert_allclose(g, num, atol=1e-3 * np.abs(g).max())
    assert 0 <= v.min() and v.max() <= 1


def test_mitsuba_normalmap_frame_matches_the_encoding(mi):
    """A quad whose u runs along +Y: Mitsuba's shading frame s = dp/du. A map normal tilted
    towards +s must brighten light coming from +Y (and not from +X)."""
    import drjit as dr

    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
    UV = np.array([[0, 0], [0, 1], [1, 1], [1, 0]], np.float32)       # u = y, v = x
    slopes = np.array([[-1.0, 0.0]], np.float32)                          # n_t ∝ (+1, 0, 1): towards +s
    nm = np.tile(encode_normals(slopes).reshape(1, 1, 3), (2, 2, 1))
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "normalmap",
                                  "normalmap": {"type": "bitmap", "data": mi.TensorXf(nm), "raw": True},
                                  "bsdf": {"type": "diffuse"}})
    m = mi.Mesh("q", 4, 2, props=props, has_vertex_normals=True, has_vertex_texcoords=True)
    p = mi.traverse(m)
    p["vertex_positions"] = dr.ravel(mi.Point3f(V.T))
    p["faces"] = dr.ravel(mi.Vector3u(F.T))
    p["vertex_texcoords"] = dr.ravel(mi.Point2f(UV.T))
    p["vertex_normals"] = dr.ravel(mi.Normal3f(np.tile([0, 0, 1], (4, 1)).astype(np.float32).T))
    p.update()
    scene = mi.load_dict({"type": "scene", "q": m})
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(0.3, 0.6, 1.0), mi.Vector3f(0, 0, -1)))
    ctx = mi.BSDFContext()

    def ev(d):
        d = np.asarray(d, float) / np.linalg.norm(d)
        return float(si.bsdf().eval(ctx, si, si.to_local(mi.Vector3f(*[float(x) for x in d])))[0][0])

    assert ev([0, 1, 1]) > 1.5 * ev([0, -1, 1])
    assert ev([1, 0, 1]) == pytest.approx(ev([-1, 0, 1]), rel=1e-4)
    # and the texture's rows are v: row 0 at v ~ 0 (our rasteriser's convention)
    tex = np.zeros((4, 4, 3), np.float32)
    tex[0] = [1, 0, 0]
    b = mi.load_dict({"type": "diffuse", "reflectance": {"type": "bitmap", "data": mi.TensorXf(tex), "raw": True,
                                                          "filter_type": "nearest"}})
    si.uv = mi.Point2f(0.5, 0.05)
    assert float(b.eval_diffuse_reflectance(si)[0][0]) == pytest.approx(1.0)
    si.uv = mi.Point2f(0.5, 0.95)
    assert float(b.eval_diffuse_reflectance(si)[0][0]) == pytest.approx(0.0)
