"""The procedural subject's template extensions (issue 16): scalp, ears, sides and neck, stitched to the face."""
import json

import numpy as np
import pytest

from mifacerf.synthetic import Template, default_subject
from mifacerf.synthetic.template import build_template
from mifacerf.synthetic.template_extensions import NECK_CUT_Y, boundary_loops, extension_mesh, face_covered
from mifacerf.registration.extensions import check_extensions, extensions_from_template


@pytest.fixture(scope="module")
def subj():
    return default_subject()


def test_extensions_cover_the_head_and_close_on_the_face(subj):
    t = subj.template
    assert {"scalp", "ear_left", "ear_right", "neck_lower"} <= set(t.extensions)
    modes = {k: (e["mode"], e["anchor"]) for k, e in t.extensions.items()}
    assert modes["scalp"] == ("rigid", "head") and modes["ear_left"] == ("rigid", "head")
    assert modes["neck_lower"] == ("driven", "body")
    ext = t.extension_ids
    kinds = np.array(t.kinds)
    assert (kinds[ext] == "extension").all() and (kinds == "extension").sum() == len(ext)
    assert ext.min() == (kinds != "extension").sum()         # appended after the face
    P = t.neutral[ext]
    assert P[:, 1].max() > 0.11 and P[:, 1].min() == pytest.approx(NECK_CUT_Y, abs=0.004)  # crown .. cut
    assert P[:, 2].min() < -0.1                                   # the back of the head
    # no gap: the only boundary loops are the mouth, the eyes and the neck cut
    loops = boundary_loops(t.triangles)
    holes = [set(map(int, h)) for h in t.holes.values()]
    other = [lp for lp in loops if set(lp) not in holes]
    assert len(other) == 1 and np.abs(t.neutral[other[0], 1] - NECK_CUT_Y).max() < 0.006
    # the extensions are exact surface points in every pose (truth binding) and move with the head
    pose = subj.pose(subj.params(head_yaw=0.4), textures=False)
    np.testing.assert_allclose(pose.template_vertices, t.positions(pose.skin_vertices, pose.parts))
    check_extensions(t.neutral, t.triangles, t.dot_ids, extensions_from_template(json.loads(t.to_json()), t.n_vertices))


def test_json_round_trip_and_old_templates_load(subj):
    t = subj.template
    d = json.loads(t.to_json())
    assert set(d["extensions"]["scalp"]) == {"vertices", "mode", "anchor", "region"}
    assert d["extensions"]["neck_lower"]["falloff"] > 0
    u = Template.from_json(json.dumps(d))
    for k, e in t.extensions.items():
        np.testing.assert_array_equal(u.extensions[k]["vertices"], e["vertices"])
    assert {tuple(x) for x in t.face_triangles} <= {tuple(x) for x in u.face_triangles}   # + border notches
    face = build_template(subj, extensions=False)       # the face alone: no "extensions" member at all
    assert "extensions" not in json.loads(face.to_json()) and face.n_vertices < t.n_vertices
    np.testing.assert_array_equal(face.triangles, t.face_triangles)


def test_face_covered_and_a_cut_above_the_face_refused(subj):
    t = build_template(subj, extensions=False)
    cov = face_covered(t.neutral + 1e-4, t.neutral, t.triangles, t.holes)
    assert cov[t.dot_ids].mean() > 0.9                    # the face's own points are inside it
    with pytest.raises(ValueError, match="neck cut at y = -0.100 m is above the face template's lowest vertex"):
        extension_mesh(subj.neutral_skin, subj.skin_faces, t.neutral, t.triangles, t.holes, neck_cut_y=-0.1)


def test_rewrite_template_keeps_the_face_as_placed_and_places_the_extensions(subj, tmp_path):
    from mifacerf.rig import LightStage, Rig, camera_ring
    from mifacerf.synthetic.hand_inputs import _user_template, rewrite_template

    cams = camera_ring([(-39, 8), (0, 8), (39, 8), (-39, -11), (0, -11), (39, -11)], width=96, height=96)
    rig = Rig(LightStage.semicircular_arm(4, 3), cams)
    face_only = build_template(subj, extensions=False)
    old = json.loads(face_only.to_json())
    rng = np.random.default_rng(1)
    for v in old["vertices"]:                      # as a user placed them: off the truth
        v["position"] = (np.asarray(v["position"]) + rng.normal(0, 5e-4, 3)).tolist()
    (tmp_path / "hand").mkdir()
    (tmp_path / "hand" / "template.json").write_text(json.dumps(old))
    path = rewrite_template(tmp_path, subj, rig)
    new = json.loads(path.read_text())
    n = len(old["vertices"])
    assert [v["position"] for v in new["vertices"][:n]] == [v["position"] for v in old["vertices"]]
    assert new["triangles"][:len(old["triangles"])] == old["triangles"] and set(new["extensions"]) == set(subj.template.extensions)
    P = np.array([v["position"] for v in new["vertices"][n:]])
    d = np.linalg.norm(P - subj.template.neutral[n:], axis=1)
    assert np.median(d) < 0.008 and d.max() < 0.05     # clicked on the truth, ~1 px noise at 96 px (3.5 mm)
    assert new["dot_radius"] == _user_template(subj)["dot_radius"]
    with pytest.raises(ValueError, match="face vertices are not the subject template's"):
        old["vertices"][0]["kind"] = "ear"
        (tmp_path / "hand" / "template.json").write_text(json.dumps(old))
        rewrite_template(tmp_path, subj, rig)
