"""A user's own head through the whole pipeline (issue 21): ``synth --subject`` → register → build →
render, on the small multi-part, UDIM, centimetre head the test builds (helpers/head_fixture), at the
``tiny`` preset; the dot-free truth, the subject folder recorded relative to the output, the CLI."""
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from helpers.head_fixture import write_head

EXPRESSIONS = ["neutral", "jawOpen"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    from mifacerf.registration import register_capture
    from mifacerf.rendering.build import build_model
    from mifacerf.synthetic.synth import synthesize

    root = tmp_path_factory.mktemp("own_head")
    head = write_head(root / "my_head")
    lines = []
    cap = synthesize(root / "synth", preset="tiny", subject_folder=head, expressions=EXPRESSIONS, progress=False,
                     subject_options={"n_dots": 120}, report=lines.append)
    reg = register_capture(cap, progress=False)
    build_model(cap, root / "model")
    return root, lines, reg


@pytest.mark.slow
def test_own_head_end_to_end(built):
    import json

    import mifacerf as mf
    from mifacerf.environment import resolve
    from mifacerf.evaluation.masks import classify_pixels, face_mask
    from mifacerf.evaluation.metrics import psnr
    from mifacerf.synthetic.scene import PART_IDS
    from mifacerf.synthetic.truth_scene import TruthRenderer

    root, lines, reg = built
    assert any(l.startswith("template: 120 dots") for l in lines)
    truth = json.loads((root / "synth" / "truth" / "truth.json").read_text())
    assert truth["subject"]["folder_relative"] == "../my_head" and truth["subject"]["options"] == {"n_dots": 120}
    # registration: the fiducials found in each expression
    rj = json.loads((root / "synth" / "capture" / "registration" / "registration.json").read_text())
    assert set(rj["expressions"]) == set(EXPRESSIONS)
    face = mf.load_model(root / "model")
    tr = TruthRenderer.from_synth(root / "synth")
    env = resolve("sky")
    cam = face.model.cameras[1]
    p = tr.expressions["jawOpen"]
    img = face.render("jawOpen", camera=cam, env=env, spp=4)
    gt = tr.render(p, cam, env, spp=32, seed=2)
    assert np.isfinite(img).all()
    tr.scene(env).set_pose(tr.subject.pose(p))
    classes = classify_pixels(tr.scene(env), cam)
    parts = classes["part"]
    for name in ("eye_left", "eye_right"):                     # the user's own eyes are in the picture
        assert np.isin(parts, [PART_IDS[name]]).all(axis=2).sum() >= 5
    mask = face_mask(classes)
    assert mask.sum() > 500
    # the face as rendered from the model against the dot-free truth (a tiny rig: 48 lights, 128 px)
    assert psnr(img, gt, mask) > 18.0
    assert (img[..., 3][mask] > 0.5).mean() > 0.9               # the model covers the face
    assert "eyes" in face.model.references                       # its eyes (and teeth, when seen) are modelled


@pytest.mark.slow
def test_dot_free_truth_and_moved_folder(built, tmp_path):
    from mifacerf.synthetic.truth_scene import TruthRenderer

    root, _, _ = built
    clean = TruthRenderer.from_synth(root / "synth")
    dotted = TruthRenderer.from_synth(root / "synth", dots=True)
    cam = clean.camera(size=64)
    a = clean.render(clean.expressions["neutral"], cam, "gradient", spp=8, seed=1)
    b = dotted.render(dotted.expressions["neutral"], cam, "gradient", spp=8, seed=1)
    assert np.abs(a - b).max() > 0.05                          # --no-dots differs from --dots
    # moved together: found by the relative path; the subject folder gone: one line naming both places
    moved = tmp_path / "moved"
    moved.mkdir()
    shutil.copytree(root / "synth", moved / "synth")
    shutil.copytree(root / "my_head", moved / "my_head")
    shutil.move(str(root / "my_head"), str(tmp_path / "away"))
    try:
        TruthRenderer.from_synth(moved / "synth")
        with pytest.raises(FileNotFoundError) as e:
            TruthRenderer.from_synth(root / "synth")
        msg = str(e.value)
        assert "\n" not in msg and str(root / "synth" / "../my_head") in msg and str(root / "my_head") in msg
    finally:
        shutil.move(str(tmp_path / "away"), str(root / "my_head"))


def test_synth_subject_options_need_a_subject(tmp_path):
    from mifacerf.cli import main

    r = CliRunner().invoke(main, ["synth", str(tmp_path / "o"), "--preset", "tiny", "--dots", "100"])
    assert r.exit_code == 2 and "--subject" in r.output
