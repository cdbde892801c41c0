"""The motion check (paper §2.1: sum of representative frames, sharpness) and the session journal."""
import itertools
import json
import zlib

import numpy as np
import pytest

from mifacerf.capture.journal import Journal, read_journal
from mifacerf.capture.motion import (SHARPNESS_METHODS, MotionCheck, coherence, highfreq_sharpness,
                                     laplacian_sharpness, reference_from, representative_lights, take_score)
from mifacerf.capture.simulation.cameras import _shift_image
from mifacerf.capture.simulation.procedural import ProceduralHead
from mifacerf.rig import CAMERA_LAYOUTS, LightStage, camera_ring


@pytest.fixture(scope="module")
def frames():
    lights = LightStage.semicircular_arm(8, 6)
    cam = camera_ring(CAMERA_LAYOUTS[3], width=64, height=64)[1]
    head = ProceduralHead(lights)
    sample = representative_lights(8, 6, 16)
    return head.render({"jaw": 0.3}, cam, sample)


def drift(frames, px):
    k = len(frames)
    return np.stack([_shift_image(f, px * i / k, 0.4 * px * i / k) for i, f in enumerate(frames)])


def test_representative_lights_cover_the_stage():
    s = representative_lights(16, 30, 32)
    assert 28 <= len(s) <= 34 and len(np.unique(s)) == len(s)
    assert set(s // 30) == set(range(16))           # every arm position
    assert len(set(s % 30)) >= 10                   # strobes spread along the arm
    assert np.array_equal(representative_lights(2, 3, 32), np.arange(6))
    sub = representative_lights(16, 30, 32, lights=np.arange(0, 480, 7))
    assert np.all(np.isin(sub, np.arange(0, 480, 7)))


@pytest.mark.parametrize("method", sorted(SHARPNESS_METHODS))
def test_motion_lowers_every_sharpness_measure(frames, method):
    still = take_score(frames, method)
    moved = take_score(drift(frames, 3.0), method)
    assert moved < 0.85 * still


@pytest.mark.parametrize("method", ["laplacian", "highfreq", "coherence"])
def test_scores_ignore_exposure(frames, method):
    assert take_score(frames * 7.5, method) == pytest.approx(take_score(frames, method), rel=1e-4)


def test_verdict_against_a_reference(frames):
    mc = MotionCheck(sample=16, threshold=0.7)
    ref = mc.scores({"cam": frames})
    still = mc.judge(mc.scores({"cam": frames}), ref)
    moved = mc.judge(mc.scores({"cam": drift(frames, 2.0)}), ref)
    assert not still.blurred and still.ratios["cam"] == pytest.approx(1.0)
    assert moved.blurred and moved.blurred_cameras == ["cam"]
    none = mc.judge(mc.scores({"cam": drift(frames, 2.0)}), None)
    assert not none.blurred and none.ratios["cam"] is None  # no reference, no verdict
    assert reference_from([{"a": 1.0, "b": 4.0}, {"a": 3.0, "b": 2.0}, {"a": 2.0}]) == {"a": 2.0, "b": 3.0}
    with pytest.raises(ValueError):
        MotionCheck(method="nope")
    with pytest.raises(ValueError):
        MotionCheck(threshold=1.5)


def test_odd_inputs_do_not_crash():
    vals = [-1.0, 0.0, 1.0, np.inf, -np.inf, np.nan]
    for a, b in itertools.product(vals, vals):
        img = np.full((6, 6, 3), a, np.float32)
        img[2:4, 2:4] = b
        for fn in (laplacian_sharpness, highfreq_sharpness):
            v = fn(img)
            assert isinstance(v, float)
        coherence(img[None])
    with pytest.raises(ValueError, match="shape"):
        take_score(np.zeros((4, 4, 3)))
    with pytest.raises(ValueError, match="unknown sharpness"):
        take_score(np.zeros((1, 4, 4, 3)), "nope")


# -------------------------------------------------------------------------------- journal
def test_journal_appends_and_reads_back(tmp_path):
    p = tmp_path / "session.jsonl"
    with Journal(p) as j:
        j.append("plan", x=1)
        j.append("frames", camera="cam0", frames=[[0, "ab"]])
    recs = read_journal(p).records
    assert [r["event"] for r in recs] == ["plan", "frames"] and recs[1]["frames"] == [[0, "ab"]]
    line = p.read_text().splitlines()[0]
    crc, text = line.split(" ", 1)
    assert int(crc, 16) == zlib.crc32(text.encode()) and json.loads(text)["x"] == 1


def test_torn_and_corrupt_lines_are_skipped_never_rewritten(tmp_path):
    p = tmp_path / "session.jsonl"
    with Journal(p) as j:
        j.append("plan")
        j.append("a")
        j.append("b")
    lines = p.read_bytes().split(b"\n")
    lines[1] = lines[1].replace(b'"a"', b'"A"')  # bit rot: CRC no longer matches
    p.write_bytes(b"\n".join(lines[:3]) + b"\n" + b'0123abcd {"event": "c", "t"')  # a torn last line
    c = read_journal(p)
    assert [r["event"] for r in c.records] == ["plan", "b"] and c.bad_lines == [2, 4]
    raw = p.read_bytes()
    with Journal(p) as j:  # appending after a torn line starts a fresh line; nothing before is touched
        j.append("d")
    assert p.read_bytes().startswith(raw)
    assert [r["event"] for r in read_journal(p).records] == ["plan", "b", "d"]
