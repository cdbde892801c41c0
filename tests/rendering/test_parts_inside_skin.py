"""Parts (eyes, teeth, the mouth's backdrop) are seen only from inside the skin: a part that pokes out
through the skin in front of the camera is replaced by the skin behind it; a part seen through an
opening stays."""
from types import SimpleNamespace

import numpy as np
import trimesh

from mifacerf.geometry.meshscene import MeshScene
from mifacerf.rendering.renderer import Renderer
from mifacerf.rig import camera_ring


def ball(radius, centre):
    b = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    b.apply_translation(centre)
    return b


def part_samples(skin, part, camera):
    """``scene_hits`` and the samples that meet the part first (more than 20 of them)."""
    hits, uv, fake = scene_hits(skin, part, camera)
    on_part = hits.valid & (hits.tri >= len(skin.faces))
    assert on_part.sum() > 20
    return hits, uv, fake, on_part


def scene_hits(skin, part, camera):
    """Hits of the camera's pixel centres on skin + part (part triangles after the skin's), back faces culled
    as the renderer does, and a stand-in renderer holding that combined scene."""
    V = np.concatenate([skin.vertices, part.vertices])
    F = np.concatenate([skin.faces, part.faces + len(skin.vertices)])
    scene = MeshScene(V, F)
    hits, uv = scene.render_hits(camera, 1)
    fake = SimpleNamespace(model=SimpleNamespace(triangles=np.asarray(skin.faces)),
                           _combined=SimpleNamespace(scene=scene, rays=scene))
    return hits, uv, fake


def test_a_part_poking_out_shows_the_skin_and_one_behind_an_opening_stays(mi):
    cam = camera_ring([(0.0, 0.0)], width=48, height=48, target=(0.0, 0.0, 0.0), face_height=0.3)[0]
    towards = cam.centre / np.linalg.norm(cam.centre)
    skin = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    # a ball centred on the skin's front: its front half pokes out of the head
    hits, uv, fake, on_part = part_samples(skin, ball(0.03, 0.1 * towards), cam)
    Renderer._parts_inside_skin(fake, hits, uv, cam)
    assert not (hits.valid & (hits.tri >= len(skin.faces))).any()   # all replaced by the skin behind
    assert hits.valid[on_part].all() and np.isfinite(hits.t[on_part]).all()
    # the replacement is the skin's own first hit from the camera
    direct, _ = MeshScene(skin.vertices, skin.faces).render_hits(cam, 1)
    np.testing.assert_array_equal(hits.tri[on_part], direct.tri[on_part])
    np.testing.assert_allclose(hits.t[on_part], direct.t[on_part], atol=1e-4)

    # the skin with a hole in front (a mouth): a ball inside, seen through it, stays
    centres = skin.triangles_center @ towards
    open_skin = trimesh.Trimesh(skin.vertices, skin.faces[centres < 0.07], process=False)
    hits, uv, fake, _ = part_samples(open_skin, ball(0.03, 0.05 * towards), cam)
    before = hits.tri.copy()
    Renderer._parts_inside_skin(fake, hits, uv, cam)
    np.testing.assert_array_equal(hits.tri, before)


def _mitsuba_hits(skin, part, camera, mi):
    """Through a Mitsuba scene of skin ('face') and part ('eye_left'), the camera's pixel-centre rays:
    (shows the face, the face point shown (N, 3), the part was hit first, the skin alone's first hit (N, 3))."""
    from mifacerf.rendering.parts import skin_in_front_of_parts

    def mesh(name, m):
        shape = mi.Mesh(name, len(m.vertices), len(m.faces))
        params = mi.traverse(shape)
        params["vertex_positions"] = mi.Float(np.asarray(m.vertices, np.float32).ravel())
        params["faces"] = mi.UInt32(np.asarray(m.faces, np.uint32).ravel())
        params.update()
        return shape

    face, eye = mesh("face", skin), mesh("eye_left", part)
    scene = mi.load_dict({"type": "scene", "face": face, "eye_left": eye})
    jj, ii = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    o, d = camera.pixel_rays(np.stack([jj.ravel(), ii.ravel()], 1).astype(float))
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(x) for x in o.T.astype(np.float32)]),
                   mi.Vector3f(*[mi.Float(x) for x in d.T.astype(np.float32)]))
    si = scene.ray_intersect(ray)
    on_face, tri, p = skin_in_front_of_parts(scene, ray, si, face, [eye])
    first_part = np.asarray(si.is_valid() & (si.shape == mi.ShapePtr(eye)))
    skin_alone = mi.load_dict({"type": "scene", "face": mesh("face", skin)}).ray_intersect(ray)
    return np.asarray(on_face), np.asarray(p).T, first_part, np.asarray(skin_alone.p).T


def test_the_scene_rule_matches_the_renderers(mi):
    """The Mitsuba-scene form (used by the facerf integrator): the same ball poking out of a sphere
    shows the skin, at the points the skin alone gives; a ball seen through an opening stays."""
    cam = camera_ring([(0.0, 0.0)], width=48, height=48, target=(0.0, 0.0, 0.0), face_height=0.3)[0]
    towards = cam.centre / np.linalg.norm(cam.centre)
    skin = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    on_face, p, first_part, expected = _mitsuba_hits(skin, ball(0.03, 0.1 * towards), cam, mi)
    assert first_part.sum() > 20
    assert on_face[first_part].all()
    np.testing.assert_allclose(p[first_part], expected[first_part], atol=1e-5)

    centres = skin.triangles_center @ towards
    open_skin = trimesh.Trimesh(skin.vertices, skin.faces[centres < 0.07], process=False)
    on_face, _, first_part, _ = _mitsuba_hits(open_skin, ball(0.03, 0.05 * towards), cam, mi)
    assert first_part.sum() > 20
    assert not on_face[first_part].any()
