"""Parts (eyes, teeth, the mouth's backdrop) are seen only from inside the skin: a part that pokes out
through the skin in front of the camera is replaced by the skin behind it; a part seen through an
opening stays."""
from types import SimpleNamespace

import numpy as np
import trimesh

from mifacerf.rendering.meshscene import MeshScene
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
    as the renderer does, and a stand-in renderer holding the skin alone."""
    V = np.concatenate([skin.vertices, part.vertices])
    F = np.concatenate([skin.faces, part.faces + len(skin.vertices)])
    hits, uv = MeshScene(V, F).render_hits(camera, 1)
    fake = SimpleNamespace(model=SimpleNamespace(triangles=np.asarray(skin.faces)),
                           _scene=MeshScene(skin.vertices, skin.faces))
    return hits, uv, fake


def test_a_part_poking_out_shows_the_skin_and_one_behind_an_opening_stays(mi):
    cam = camera_ring([(0.0, 0.0)], width=48, height=48, target=(0.0, 0.0, 0.0), face_height=0.3)[0]
    towards = cam.centre / np.linalg.norm(cam.centre)
    skin = trimesh.creation.icosphere(subdivisions=3, radius=0.1)
    # a ball centred on the skin's front: its front half pokes out of the head
    hits, uv, fake, on_part = part_samples(skin, ball(0.03, 0.1 * towards), cam)
    Renderer._parts_inside_skin(fake, hits, uv, cam, np.asarray(skin.vertices))
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
    Renderer._parts_inside_skin(fake, hits, uv, cam, np.asarray(open_skin.vertices))
    np.testing.assert_array_equal(hits.tri, before)
