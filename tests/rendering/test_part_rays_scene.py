"""The scene the parts' rays are cast into (``CombinedScene.rays``): the skin curved only round the parts —
the sub-faces there the whole surface's own, the rest flat — so that Mitsuba rebuilds a smaller BVH each
pose; checked against the whole curved scene with Mitsuba's own intersections."""
import numpy as np
import trimesh

from mifacerf.rendering.parts import CombinedScene


def head_and_eye():
    skin = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    skin.apply_scale([1.0, 1.25, 0.9])                    # an ellipsoid: normals are not the positions
    eye = trimesh.creation.icosphere(subdivisions=2, radius=0.012)
    eye.apply_translation([0.03, 0.02, 0.078])            # just inside the front, as an eyeball
    return skin, eye


def test_the_parts_rays_meet_the_whole_curved_surface_round_the_parts(mi):
    skin, eye = head_and_eye()
    meshes = {"eye_left": (np.asarray(eye.vertices), np.asarray(eye.faces))}
    V, F = np.asarray(skin.vertices), np.asarray(skin.faces)
    cs = CombinedScene(V, F, meshes, curved=3, ray_radius=0.02)
    whole, rays = cs.scene, cs.rays
    near = rays.tessellation.curved[: len(F)]
    assert 0 < near.sum() < 0.25 * len(F) and not rays.tessellation.curved[len(F):].any()
    assert len(rays.tessellation.faces) < 0.4 * len(whole.tessellation.faces)

    # posed together: a turn and a shift of everything
    a = 0.2
    R = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, [0.01, -0.02, 0.0]
    cs.set_pose(V @ R.T + T[:3, 3], {"eye_left": T}, lazy=True)
    cs.rays.commit()
    assert np.array_equal(whole.vertices, rays.vertices)

    # rays from the eye's surface in every direction outwards, as its shadow rays are cast
    rng = np.random.default_rng(1)
    centre = T[:3, :3] @ np.array([0.03, 0.02, 0.078]) + T[:3, 3]
    n = rng.normal(size=(4000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = centre + 0.0122 * n
    d = n + 0.6 * rng.normal(size=n.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where((d * n).sum(1, keepdims=True) < 0, -d, d)
    hw, hr = whole.trace(p, d), rays.trace(p, d)
    on_near = hw.valid & (hw.tri < len(F)) & near[np.maximum(hw.tri, 0)]
    assert on_near.sum() > 500
    # where the whole surface's hit is skin curved in both: the same triangle, point and distance
    assert np.array_equal(hr.tri[on_near], hw.tri[on_near])
    np.testing.assert_allclose(hr.t[on_near], hw.t[on_near], atol=1e-6)
    np.testing.assert_allclose(hr.bary[on_near], hw.bary[on_near], atol=1e-5)
    # farther off the flat skin answers the same blocked / free for nearly every ray
    assert (hr.valid == hw.valid).mean() > 0.995
    # without a radius, or flat, the parts' rays go into the whole scene
    for kw in ({"curved": 3}, {"curved": 1, "ray_radius": 0.02}):
        other = CombinedScene(V, F, meshes, **kw)
        assert other.rays is other.scene
