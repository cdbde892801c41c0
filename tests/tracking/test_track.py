"""Tracking the clean performance: dots, head pose, eyes, lips; it never needs the truth."""
import json
import shutil

import numpy as np
import pytest

from helpers.tracking import copy_performance
from openwatch import watch_opens

# every test here needs the tracking world (tests/tracking/conftest.py), a fixture of more than 20 s
pytestmark = pytest.mark.slow


def test_clean_track_against_truth(world):
    from mifacerf.evaluation.tracking import evaluate_track

    tr = world["track"]
    n, T = tr.n_frames, tr.vertices.shape[1]
    assert tr.vertices.shape == (n, T, 3) and np.isfinite(tr.vertices).all()
    assert tr.status.shape == (n, T) and set(np.unique(tr.status)) <= {0, 1}
    assert (tr.camera_status == 0).all()
    e = evaluate_track(tr, world["out"])
    # tracked dots: sub-pixel (pixel footprints of the 96 px video)
    assert e["dot_error"]["median"] < 0.35 and e["dot_error"]["p95"] < 1.5, e["dot_error"]
    # untracked dots (seen by fewer than two cameras) are marked, and filled in near the truth
    assert e["dot_frames_tracked_of_seen"] > 0.8, e
    assert e["dots_tracked_whole_sequence"] > 0.6 * e["dots_seen_throughout"], e
    assert e["dot_error_untracked"]["median"] < 3.0
    assert e["head_pose"]["rotation_deg"]["p95"] < 1.0
    assert e["gaze_deg"]["keyframes"]["median"] < 6.0
    for name in ("lip_upper", "lip_lower"):
        assert e["margins"][name]["keyframes"]["median"] < 1.5, (name, e["margins"][name])
        assert e["margins"][name]["in_between"]["median"] < 2.5, (name, e["margins"][name])
    assert (world["track"].root / "evaluation.json").exists()
    meta = tr.meta
    assert meta["time_s"]["per_frame_mean"] > 0 and meta["reprojection_px"]["median"] < 0.5


def test_tracking_reads_only_the_performance_folder(world, tmp_path):
    """The performance copied away from the synth output (no truth/ anywhere near it) tracks the same;
    and while tracking in place, no file under truth/ is opened."""
    from mifacerf.tracking.track import Track, track_performance

    lone = copy_performance(world["perf"], tmp_path / "alone" / "performance")
    with watch_opens(world["out"] / "truth") as opened:
        a = Track(track_performance(lone, tmp_path / "t1", model=world["model"], progress=False, frames=14))
        b = Track(track_performance(world["perf"], tmp_path / "t2", model=world["model"], progress=False,
                                     frames=14))
    assert opened == []
    assert np.allclose(a.vertices, b.vertices) and np.array_equal(a.dot_status, b.dot_status)
    # frame-by-frame tracking does not look ahead: the first frames match the full track's
    assert np.array_equal(a.dot_status, world["track"].dot_status[:14])


def test_smoothing_reduces_jitter_without_bias(world, tmp_path):
    from mifacerf.evaluation.tracking import evaluate_track
    from mifacerf.tracking.track import Track, track_performance
    from mifacerf.tracking.track3d import Options

    raw = Track(track_performance(world["perf"], tmp_path / "raw", model=world["model"],
                                  options=Options(smooth_sigma=0.0), progress=False))
    st = raw.dot_status == 1
    both = st[1:-1] & st[2:] & st[:-2]
    acc = lambda X: np.linalg.norm(X[2:] - 2 * X[1:-1] + X[:-2], axis=-1)[both]  # noqa: E731
    assert acc(world["track"].dots).mean() < 0.7 * acc(raw.dots).mean()
    e_raw = evaluate_track(raw, world["out"], write=False, coverage=False)
    e_smooth = evaluate_track(world["track"], world["out"], write=False, coverage=False)
    assert e_smooth["dot_error"]["median"] <= e_raw["dot_error"]["median"] * 1.05


def test_track_cli_and_errors(world, tmp_path):
    from click.testing import CliRunner

    from mifacerf.cli import main

    r = CliRunner().invoke(main, ["track", str(world["perf"]), "-o", str(tmp_path / "t"), "--frames", "6",
                                  "--model", str(world["model"]), "--overlay", "5"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "t" / "track.npz").exists() and not (tmp_path / "t" / "evaluation.json").exists()
    assert len(list((tmp_path / "t").glob("overlay_F00005_*.png"))) == 3
    # the comparison with the truth (and the overlays with the true dots) is the evaluation's
    r = CliRunner().invoke(main, ["evaluate", "tracking", str(world["out"]), str(tmp_path / "t"), "--overlay", "4"])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "t" / "evaluation.json").exists() and "dot error" in r.output
    assert len(list((tmp_path / "t").glob("overlay_F00004_*.png"))) == 3
    # not a performance folder / a missing template: clear errors
    r = CliRunner().invoke(main, ["track", str(tmp_path)])
    assert r.exit_code != 0 and "manifest.json" in r.output
    broken = copy_performance(world["perf"], tmp_path / "broken")
    (broken / "hand" / "template.json").unlink()
    r = CliRunner().invoke(main, ["track", str(broken)])
    assert r.exit_code != 0 and "template" in r.output
