"""The two tiers of camera weights (mifacerf.rendering.chunks): primary (cameras that see a vertex or
a triangle round it, occlusion decided per pixel) and fallback (the paper's per-vertex rule)."""
import numpy as np
import pytest

from mifacerf.camera import Camera
from mifacerf.rendering.chunks import plan_frame, seen_near


def test_seen_near_spreads_visibility_over_the_triangles_round_a_vertex():
    # a strip 0-1-2-3-4: triangles (0,1,2), (1,2,3), (2,3,4); camera 0 sees vertex 0 only, camera 1 none
    tri = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]])
    vis = np.zeros((2, 5), bool)
    vis[0, 0] = True
    near = seen_near(vis, tri)
    np.testing.assert_array_equal(near[0], [True, True, True, False, False])
    assert not near[1].any()
    assert seen_near(np.ones((1, 5), bool), tri).all()


def test_a_captured_view_of_a_captured_expression_keeps_its_own_camera(toy_model):
    """At a capture camera rendering its captured expression, every vertex of a triangle that camera
    sees takes its weight from that camera alone (primary tier); the per-vertex rule (fallback tier)
    hands the hidden corners of silhouette triangles to other cameras."""
    model = toy_model
    s, c = 0, 1
    W = np.zeros((model.n_vertices, len(model.expressions)))
    W[:, s] = 1.0
    plan = plan_frame(model, model.vertices[s], W, model.cameras[c])
    primary = np.zeros((len(model.cameras), model.n_vertices))
    fallback = np.zeros_like(primary)
    for ch in plan.chunks:
        assert ch.s == s
        primary[ch.c], fallback[ch.c] = ch.weights, ch.fallback
    near = seen_near(model.visible[s], model.triangles)[c]
    np.testing.assert_allclose(primary[c, near], 1.0)
    hidden_corner = near & ~model.visible[s][c]
    assert hidden_corner.any()                       # silhouette triangles exist in this view
    assert (fallback[c, hidden_corner] < 1.0).all()  # the paper's rule: another camera there
    np.testing.assert_allclose(primary.sum(0)[near], 1.0)
    np.testing.assert_allclose(fallback.sum(0)[model.visible[s].any(0)], 1.0)


def _frame(depth_ok: tuple[bool, bool], weights: tuple, mi):
    """A LitFrame of one triangle facing a camera, with two chunks of constant colour (red, green):
    ``depth_ok`` says whether each chunk's depth map matches the surface; ``weights`` are each
    chunk's (primary, fallback) weights at every vertex."""
    from mifacerf.rendering.frame import LitFrame

    cam = Camera.look_at("c", [0, 0, 1.0], [0, 0, 0], width=16, height=16, focal=40.0)
    target = np.array([[-0.5, -0.5, 0.0], [0.5, -0.5, 0.0], [0.0, 0.5, 0.0]])
    chunks = []
    for k, (colour, ok, (a, f)) in enumerate(zip(([1, 0, 0], [0, 1, 0]), depth_ok, weights)):
        image = np.zeros((16, 16, 4), np.float32)
        image[..., :3] = colour
        image[..., 3] = 1.0
        depth = np.full((16, 16), 1.0 if ok else 5.0, np.float32)  # the plane is ~1 m away
        chunks.append({"s": 0, "c": k, "weights": np.full(3, a), "fallback": np.full(3, f), "image": image,
                       "depth": depth, "camera": cam})
    return LitFrame(target, np.array([[0, 1, 2]]), chunks, {0: target}, depth_tolerance=0.05)


@pytest.mark.parametrize("depth_ok, weights, expected, fell_back", [
    ((True, True), ((1, 0), (0, 1)), [1, 0, 0], False),    # primary seen: primary only
    ((False, True), ((1, 0), (0, 1)), [0, 1, 0], False),   # primary hidden: fallback seen
    ((False, False), ((1, 0), (0, 1)), [0, 1, 0], True),   # none seen: fallback weights, no depth test
    ((True, True), ((1, 1), (1, 0)), [0.5, 0.5, 0], False),
])
def test_shading_uses_the_first_tier_that_sees_the_point(mi, depth_ok, weights, expected, fell_back):
    frame = _frame(depth_ok, weights, mi)
    tri = mi.UInt32([0, 0])
    bary = mi.Vector3f(mi.Float([1 / 3, 0.2]), mi.Float([1 / 3, 0.3]), mi.Float([1 / 3, 0.5]))
    colour, covered, fb = frame.shade(tri, bary)
    np.testing.assert_allclose(np.asarray(colour).reshape(3, -1).T, [expected] * 2, atol=1e-6)
    assert np.asarray(covered).all()
    assert (np.asarray(fb) == fell_back).all()
