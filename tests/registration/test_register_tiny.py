"""End to end on the synthetic subject at the ``tiny`` preset: synth → register → compare with the truth.

Registration must read only the capture folder: the truth is moved out of the synth folder before
registering, and an audit hook fails the test if any file under it is opened while registering.

Thresholds are honest for ``tiny`` (three cameras at 128 px, 2.3 mm per pixel, dots ~5 px apart): a
fiducial must be seen by two views to be triangulated, which only ~55 % of them are; the draft
preset's numbers are in docs/registration.md.
"""
import numpy as np
import pytest
from helpers.capture import tiny_capture_without_truth
from openwatch import watch_opens

TINY_EXPRESSIONS = ["neutral", "viseme_aa", "head_turn_left"]
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from mifacerf.registration import register_capture

    cap, truth = tiny_capture_without_truth(tmp_path_factory.mktemp("tiny"), TINY_EXPRESSIONS)
    with watch_opens(truth) as opened:
        out = register_capture(cap, progress=False)
    return cap, truth, out, opened


@pytest.mark.slow
def test_tiny_registration_against_truth(tiny):
    from mifacerf.evaluation.registration import evaluate

    cap, truth, out, opened = tiny
    assert opened == [], "registration opened ground-truth files"
    res = evaluate(cap, truth, out)
    rows = res["per_expression"]
    assert sorted(rows) == sorted(TINY_EXPRESSIONS)
    for name, r in rows.items():
        # a fiducial needs two views; tiny's three 128-px cameras see ~55 % of them twice, and the
        # jaw of an open mouth (registered from the neutral alone here) is the hardest part
        assert r["registered_of_seen"] >= 0.5, name
        assert r["median_px"] < 0.4, name
        assert r["misregistered_fraction"] < 0.15, name      # registered > 3 px from the truth
        assert r["dot_response_after"] < 0.25 * r["dot_response_before"], name
        assert r["eye_centre_m"] < 0.003, name
    assert rows["head_turn_left"]["head_rotation_deg"] < 1.0
    # the marked point + the jaw's rotation from the chin fiducials, on the user's template strip
    # (the paper's head rotation would be off by the whole 15° of the open jaw)
    assert rows["viseme_aa"]["lower_teeth_m"] < 0.008
    assert rows["viseme_aa"]["lower_teeth_rotation_deg"] < 5.0


@pytest.mark.slow
def test_tiny_outputs_feed_the_model_build(tiny):
    """The registration folder holds what ``mifacerf build`` reads (template keys, arrays, patches)."""
    from mifacerf.formats.registration import Registration
    from mifacerf.rendering.build import template_arrays

    cap, truth, out, _ = tiny
    reg = Registration(out)
    t = template_arrays(reg.template)
    assert t["fiducial"].sum() == 300 and t["n_vertices"] == len(reg.expression("neutral").vertices)
    assert set(t["regions"]) >= {"forehead", "mouth"}
    for name in TINY_EXPRESSIONS:
        r = reg.expression(name)
        assert r.uv.shape == (3, t["n_vertices"], 2) and r.visible.shape == (3, t["n_vertices"])
        assert np.isfinite(r.eye_centres).all() and np.isfinite(r.teeth).all()
        assert reg.dotfree_patch(name, "cam1") is not None
    assert np.allclose(reg.expression("neutral").head_pose, np.eye(4))
