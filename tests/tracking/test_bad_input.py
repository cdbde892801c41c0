"""Bad input: dropped and duplicated frames, a camera that goes dark, a dot lost for many frames.

Tracking must continue, mark what it could not track, and recover when the data returns.
"""
import shutil

import numpy as np
import pytest

from helpers.tracking import as_recorded, copy_performance, paint_out_dot

# every test here needs the tracking world (tests/tracking/conftest.py), a fixture of more than 20 s
pytestmark = pytest.mark.slow

MODEL = {"path": None}


@pytest.fixture(autouse=True)
def _model(world):
    MODEL["path"] = world["model"]


def _track(perf, out):
    from mifacerf.tracking.track import Track, track_performance

    as_recorded(perf)          # the damage made here is the cameras' (recorded so), not later bit rot
    return Track(track_performance(perf, out, model=MODEL["path"], progress=False))


def _err_px(tr, world):
    from mifacerf.geometry.footprint import centre_footprint as footprint
    from mifacerf.formats.performance import PerformanceFolder
    from mifacerf.synthetic.recording import read_truth

    t = read_truth(world["out"])["template_vertices"][:, tr.dot_ids]
    return np.linalg.norm(tr.dots - t, axis=-1) / footprint(PerformanceFolder(world["perf"]).cameras)


def test_dropped_and_duplicated_frames(world, tmp_path):
    perf = copy_performance(world["perf"], tmp_path / "perf")
    fr = perf / "frames"
    (fr / "cam1" / "F00014.exr").unlink()                                   # dropped
    (fr / "cam1" / "F00015.exr").write_bytes(b"not an exr")                 # corrupt = dropped
    shutil.copy(fr / "cam2" / "F00016.exr", fr / "cam2" / "F00017.exr")     # duplicated
    for cam in ("cam0", "cam1", "cam2"):                                    # a whole frame lost
        (fr / cam / "F00019.exr").unlink()
    tr = _track(perf, tmp_path / "track")
    cs = tr.camera_status
    assert cs[14, 1] == 1 and cs[15, 1] == 1 and cs[17, 2] == 2 and (cs[19] == 1).all()
    assert (cs[:14] == 0).all() and cs[16, 2] == 0
    problems = " ".join(tr.meta["camera_problems"])
    assert "missing" in problems and "duplicate" in problems
    assert "19" in tr.meta["frames_without_two_usable_cameras"]
    # the duplicate's stale image was not used; the lost frame is marked untracked, not dropped
    assert np.isnan(tr.uv[17, 2]).all() and (tr.dot_status[19] == 0).all()
    assert np.isfinite(tr.vertices[19]).all()
    # and tracking recovers: after the damage, as many dots as in the clean track
    clean = world["track"].dot_status
    assert tr.dot_status[20:].sum() >= 0.95 * clean[20:].sum()
    e = _err_px(tr, world)
    assert np.median(e[tr.dot_status == 1]) < 0.4
    assert np.median(e[19]) < 1.5      # the lost frame: predicted from both sides


def test_camera_goes_dark(world, tmp_path):
    from mifacerf.imageio import read_exr, write_exr

    perf = copy_performance(world["perf"], tmp_path / "perf")
    dark = range(13, 19)
    rng = np.random.default_rng(0)
    for f in dark:
        p = perf / "frames" / "cam0" / f"F{f:05d}.exr"
        img = read_exr(p)
        write_exr(p, np.abs(0.01 * img + 0.002 * rng.standard_normal(img.shape)).astype(np.float32))
    tr = _track(perf, tmp_path / "track")
    assert (tr.camera_status[list(dark), 0] == 3).all() and (tr.camera_status[19:, 0] == 0).all()
    assert "dark" in " ".join(tr.meta["camera_problems"])
    assert np.isnan(tr.uv[list(dark), 0]).all()                   # nothing taken from the dark camera
    assert np.isfinite(tr.uv[20:, 0]).any(axis=-1).sum() > 0.8 * np.isfinite(world["track"].uv[20:, 0]).any(axis=-1).sum()
    # the other two cameras carry the dots they both see; the rest are marked, not guessed silently
    during = tr.dot_status[list(dark)]
    assert 0 < during.mean() < world["track"].dot_status[list(dark)].mean()
    e = _err_px(tr, world)
    assert np.median(e[tr.dot_status == 1]) < 0.4


def test_dot_lost_for_many_frames_is_marked_and_recovered(world, tmp_path):
    from mifacerf.formats.performance import PerformanceFolder
    from mifacerf.synthetic.recording import read_truth

    clean = world["track"]
    pf = PerformanceFolder(world["perf"])
    truth = read_truth(world["out"])["template_vertices"][:, clean.dot_ids]
    # a dot tracked from all three cameras throughout the clean run, near the middle of the face
    seen3 = np.isfinite(clean.uv[..., 0]).all(axis=1).all(axis=0) & (clean.dot_status == 1).all(0)
    cand = np.flatnonzero(seen3)
    assert len(cand) > 0
    d = int(cand[np.argmin(np.abs(truth[0, cand, 0]))])
    perf = copy_performance(world["perf"], tmp_path / "perf")
    lost = range(6, 18)                       # 12 frames: 0.2 s
    for f in lost:
        for cam in pf.cameras:
            paint_out_dot(perf, cam, f, cam.project(truth[f, d][None])[0][0])
    tr = _track(perf, tmp_path / "track")
    st = tr.dot_status[:, d]
    assert (st[list(lost)] == 0).all(), st                # marked untracked while it is gone
    assert (st[:6] == 1).all()
    assert (st[20:] == 1).all(), st                       # found again when it returns
    assert tr.redetected[18:21, d].any()
    # while lost it follows its neighbours (and its own offset), and nothing else was disturbed
    e = _err_px(tr, world)
    assert e[list(lost), d].max() < 2.5, e[list(lost), d]
    others = np.ones(tr.dot_status.shape[1], bool)
    others[d] = False
    assert (tr.dot_status[:, others] == clean.dot_status[:, others]).mean() > 0.97
