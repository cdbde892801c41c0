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


def test_material_self_visibility_is_a_parameter(toy_model, mi):
    """facerf_bsdf's self_visibility (default on) reaches the material; off keeps the captured field as is."""
    from mifacerf.variant import ensure_plugins

    ensure_plugins()
    for flag in (True, False):
        scene = mi.load_dict({"type": "scene", "face": {"type": "facerf_face", "model": str(toy_model.root),
                                                        "bsdf": {"type": "facerf_bsdf", "self_visibility": flag}}})
        bsdf = scene.shapes()[0].bsdf()
        assert bsdf.state.self_visibility is flag
