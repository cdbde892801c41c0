"""The output folders of 'mifacerf drive' and 'mifacerf track' are transactions (formats.files.OutputFolder):
written beside, swapped in complete, locked (a second run on one folder exits 3), never replacing a folder
that is not theirs; a failure, a full disk or a SIGKILL at any moment leaves the previous complete folder or
the new one. 'mifacerf render -o' writes its EXR and PNG complete before either replaces the old ones."""
import errno
import json
import os
import random

import numpy as np
import pytest
from click.testing import CliRunner

from mifacerf.errors import EXIT_REFUSED, RefusedError
from mifacerf.formats.files import OutputFolder, repair_if_needed
from mifacerf.tracking.track import TrackError

from .faults import ENOSPC, hold_lock, killed, run_child, siblings, snapshot, start_child
from .stand_ins import drive_state, make_track, run_drive


@pytest.fixture
def driven(tmp_path):
    """(track folder, drive folder driven once with shade 0.5, its snapshot)."""
    track = make_track(tmp_path / "track")
    out = tmp_path / "drive"
    run_drive(str(track), str(out))
    return track, out, snapshot(out)


def old_or_new(out, old):
    """After the repair the next drive (or any reader) does first: the drive folder is byte-identical to
    ``old`` ("old") or a complete newer drive ("new")."""
    repair_if_needed(out, "drive.json", TrackError)
    assert siblings(out) == [], siblings(out)
    if snapshot(out) == old:
        return "old"
    drive_state(out)
    return "new"


def test_a_failed_drive_keeps_the_previous_one(driven):
    track, out, old = driven
    with pytest.raises(RuntimeError, match="injected failure rendering frame 3"):
        run_drive(str(track), str(out), fail_at=3, shade=0.9)
    assert snapshot(out) == old and siblings(out) == []       # frames 0-2 were not overwritten
    run_drive(str(track), str(out), shade=0.9)                # and the lock was released
    assert old_or_new(out, old) == "new"


@pytest.mark.parametrize("nth", [1, 6])
def test_a_full_disk_during_drive_keeps_the_previous_one(driven, monkeypatch, nth):
    track, out, old = driven
    monkeypatch.setattr(os, "fsync", ENOSPC(nth))
    with pytest.raises(OSError) as exc:
        run_drive(str(track), str(out), shade=0.9)
    assert exc.value.errno == errno.ENOSPC
    assert snapshot(out) == old and siblings(out) == []


def test_sigkill_during_drive_at_every_rename_and_at_random_moments(driven):
    track, out, old = driven
    args = {"track": str(track), "out": str(out), "shade": 0.9, "slow": 0.05}
    outcomes = []
    for n in (1, 2, 3):            # killed before: building -> ready, drive -> old, ready -> drive
        p = run_child("drive", {**args, "shade": 0.6 + 0.1 * n}, f"call:rename:{n}:{out.name}")
        assert killed(p), p.stderr[-2000:]
        outcomes.append(old_or_new(out, old))
        old = snapshot(out)
    assert outcomes == ["old", "new", "new"]
    rnd = random.Random(15)
    for k in range(2):
        p = start_child("drive", {**args, "shade": 0.2 + 0.1 * k}, f"time:{rnd.uniform(0.5, 2.5):.3f}")
        p.wait(timeout=120)
        p.stdout.read(), p.stderr.read()
        if old_or_new(out, old) == "new":
            old = snapshot(out)


def test_two_drives_on_one_folder_the_second_is_refused_with_exit_3(driven, monkeypatch, tmp_path):
    from mifacerf.cli import main
    from mifacerf.rendering import api

    from .stand_ins import StandInFace

    track, out, old = driven
    release = hold_lock(out, TrackError)
    try:
        with pytest.raises(TrackError, match=r"locked by PID \d+ .* \(another drive is running") as exc:
            run_drive(str(track), str(out), shade=0.9)
        assert isinstance(exc.value, RefusedError)
        (tmp_path / "model").mkdir()
        monkeypatch.setattr(api, "load_model", lambda root: StandInFace(root))
        r = CliRunner().invoke(main, ["drive", str(track), "--model", str(tmp_path / "model"), "-o", str(out),
                                      "--env", "flat"])
        assert r.exit_code == EXIT_REFUSED, r.output
        assert "locked by PID" in r.stderr and "Traceback" not in r.output
    finally:
        release()
    assert snapshot(out) == old


def test_drive_never_replaces_a_folder_that_is_not_a_drive(driven, tmp_path):
    track, _, _ = driven
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep me")
    with pytest.raises(TrackError, match="holds files but no drive.json, so it is not a drive folder"):
        run_drive(str(track), str(mine))
    assert snapshot(mine) == {"notes.txt": b"keep me"} and siblings(mine) == []


# ------------------------------------------------------------------ track
def _performance(root, template=None):
    from mifacerf.formats.performance import PerformanceWriter
    from mifacerf.rig import camera_ring

    cams = camera_ring([(-20, 0), (20, 0)], width=6, height=5)
    w = PerformanceWriter(root, cams, 30.0, 2, template or {"schema": "mifacerf.template/1"})
    rng = np.random.default_rng(0)
    for f in range(2):
        for c in cams:
            w.write(c.name, f, rng.random((5, 6, 3)).astype(np.float32))
    return w.finish()


@pytest.fixture
def tracked(tmp_path):
    """(performance whose template is unusable, PERF/track as a complete earlier track with a drive inside)."""
    perf = _performance(tmp_path / "perf")
    track = make_track(perf / "track")
    run_drive(str(track), str(track / "drive"))
    return perf, track, snapshot(track)


def test_a_failed_track_keeps_the_previous_one_and_its_drive(tracked):
    from mifacerf.tracking.track import track_performance

    perf, track, old = tracked
    with pytest.raises(TrackError, match="no usable template"):
        track_performance(perf, progress=False)
    assert snapshot(track) == old and siblings(track) == []


def test_two_tracks_on_one_folder_the_second_is_refused_with_exit_3(tracked):
    from mifacerf.cli import main

    perf, track, old = tracked
    release = hold_lock(track, TrackError)
    try:
        r = CliRunner().invoke(main, ["track", str(perf)])
        assert r.exit_code == EXIT_REFUSED, r.output
        assert "locked by PID" in r.stderr and "another track is running" in r.stderr
    finally:
        release()
    assert snapshot(track) == old


def test_track_never_replaces_a_folder_that_is_not_a_track(tracked, tmp_path):
    from mifacerf.tracking.track import track_performance

    perf, _, _ = tracked
    with pytest.raises(TrackError, match="holds files but no track.json, so it is not a track folder"):
        track_performance(perf, perf, progress=False)            # 'track -o PERF'
    assert (perf / "manifest.json").exists() and siblings(perf) == []


def test_an_interrupted_swap_is_finished_when_the_track_is_opened(tracked):
    """Killed between 'TRACK -> old' and 'ready -> TRACK': the next reader (Track) finishes the swap."""
    from mifacerf.tracking.track import Track

    perf, track, old = tracked
    ready = track.parent / ".track.ready-1-x"
    ready.mkdir()
    make_track(ready, seed=1)
    track.rename(track.parent / ".track.old-1-x")
    tr = Track(track)
    assert tr.n_frames == 6 and siblings(track) == []
    assert not (track / "drive").exists()          # (the carry-over happens before the swap, in finish)


# ------------------------------------------------------------------ the transaction itself
def test_output_folder_sigkill_at_every_rename_keeps_old_or_new_and_carries_what_is_not_its_own(tmp_path):
    target = tmp_path / "out"
    target.mkdir()
    (target / "done.json").write_text("{}")
    (target / "a.txt").write_text("old")
    (target / "stale.txt").write_text("old only")
    (target / "keep").mkdir()
    (target / "keep" / "x.bin").write_bytes(b"another command's output")
    old = snapshot(target)
    new = {"a.txt": b"new", "sub/b.txt": b"new b", "done.json": b"{}", "keep/x.bin": b"another command's output"}
    outcomes = []
    for n in (1, 2, 3, None):
        kill = f"call:rename:{n}:{target.name}" if n else "none"
        p = run_child("output", {"target": str(target), "files": {"a.txt": "new", "sub/b.txt": "new b"}}, kill)
        assert killed(p) == bool(n), p.stderr[-2000:]
        repair_if_needed(target, "done.json", OSError)   # what the next run (or a reader) does first
        assert siblings(target) == [], siblings(target)
        now = snapshot(target)
        assert now in (old, new), now
        outcomes.append("old" if now == old else "new")
    assert outcomes == ["old", "new", "new", "new"]


def test_output_folder_dropped_unfinished_is_discarded_and_unlocked(tmp_path):
    target = tmp_path / "out"
    o = OutputFolder(target, "done.json", ValueError)
    (o.root / "half.txt").write_text("half")
    building = o.root
    del o                                           # (an exception unwinding the writer's frame)
    assert not building.exists() and not target.exists()
    with OutputFolder(target, "done.json", ValueError, wait=False) as o:
        with pytest.raises(ValueError, match=r"done.json: not written; the new run folder is incomplete"):
            o.finish()
    assert not target.exists() and siblings(target) == []


# ------------------------------------------------------------------ mifacerf render -o
def _render(*args):
    from mifacerf.cli import main

    return CliRunner().invoke(main, ["render", *map(str, args)])


def _pair(tmp_path):
    out = tmp_path / "render.exr"
    out.write_bytes(b"old exr")
    out.with_suffix(".png").write_bytes(b"old png")
    scene = tmp_path / "scene.xml"
    scene.write_text("<scene version='3.0.0'><this is not a scene/></scene>")
    return out, scene, snapshot(tmp_path)


def test_two_renders_to_one_output_the_second_is_refused_with_exit_3_and_no_lock_file_is_left(tmp_path):
    """'mifacerf render -o F' holds F's lock while it renders: a second render to F is refused (exit 3) and
    leaves F's EXR and PNG as they were (else one render's EXR could end beside the other's PNG). The lock
    file is deleted when the holder ends: nothing is left beside the user's files."""
    out, scene, before = _pair(tmp_path)
    release = hold_lock(out, ValueError, ephemeral=True)
    try:
        assert (tmp_path / ".render.exr.lock").exists()
        r = _render(scene, "-o", out)
        assert r.exit_code == EXIT_REFUSED, r.output
        assert "render.exr: locked by PID" in r.stderr and "Traceback" not in r.output
    finally:
        release()
    assert snapshot(tmp_path) == before                  # no lock file, no temporary left
    r = _render(scene, "-o", out)                          # free again: this one runs (and fails on the scene)
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    assert snapshot(tmp_path) == before


def test_an_ephemeral_lock_deleted_by_its_holder_is_never_held_twice(tmp_path):
    """An ephemeral lock file is deleted by its holder on release; a waiter that had opened it before must not
    hold the deleted file's lock while another holds the new file's (the inode check in FolderLock.acquire).
    Four threads (flock treats each one's descriptor as another holder) take it in turns, 25 times each."""
    import threading
    import time

    from mifacerf.formats.files import FolderLock

    target = tmp_path / "r.exr"
    holders, most, errors = [0], [0], []
    guard = threading.Lock()

    def turns():
        try:
            for _ in range(25):
                with FolderLock(target, ValueError, wait=30, ephemeral=True):
                    with guard:
                        holders[0] += 1
                        most[0] = max(most[0], holders[0])
                    time.sleep(0.002)
                    with guard:
                        holders[0] -= 1
        except Exception as exc:  # noqa: BLE001 (reported below)
            errors.append(exc)
    threads = [threading.Thread(target=turns) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == [] and most[0] == 1, (errors, most)
    assert os.listdir(tmp_path) == []


def test_sigkill_at_every_rename_of_a_render_output_leaves_the_old_pair_or_the_new(tmp_path):
    """replace_together (render -o's EXR + PNG): killed before, between or after its renames, the pair is —
    once the next render has finished the journal — both old or both new, never one of each."""
    from mifacerf.formats.files import finish_replacing

    outcomes = []
    for n in (1, 2, 3, None):          # killed just before 1: the journal's own rename, 2: the PNG's, 3: the EXR's
        d = tmp_path / f"k{n}"
        d.mkdir()
        (d / "r.exr").write_bytes(b"old exr")
        (d / "r.png").write_bytes(b"old png")
        (d / ".r.exr.1-a.tmp.exr").write_bytes(b"new exr")
        (d / ".r.exr.1-a.tmp.png").write_bytes(b"new png")
        journal = d / ".r.exr.replacing"
        p = run_child("replace", {"pairs": [[str(d / ".r.exr.1-a.tmp.png"), str(d / "r.png")],
                                            [str(d / ".r.exr.1-a.tmp.exr"), str(d / "r.exr")]],
                                  "journal": str(journal)}, f"call:replace:{n}" if n else "none")
        assert killed(p) == bool(n), p.stderr[-2000:]
        if n == 3:
            assert journal.exists() and (d / "r.png").read_bytes() == b"new png" \
                and (d / "r.exr").read_bytes() == b"old exr"          # the window the journal closes
        finish_replacing(journal)                          # what the next render to r.exr does first
        pair = ((d / "r.exr").read_bytes(), (d / "r.png").read_bytes())
        assert pair in ((b"old exr", b"old png"), (b"new exr", b"new png")), pair
        assert not journal.exists()
        outcomes.append("old" if pair[0] == b"old exr" else "new")
    assert outcomes == ["old", "new", "new", "new"]


def test_the_next_render_finishes_a_killed_renders_pair_and_removes_its_temporaries(tmp_path):
    """The state a render killed between its two renames leaves (the new PNG in place, the new EXR under its
    temporary name, the journal), plus the temporaries of a render killed before its renames: the next
    render to that output (here one that then fails on its scene) first makes the pair whole and new."""
    out, scene, _ = _pair(tmp_path)
    out.with_suffix(".png").write_bytes(b"new png")
    (tmp_path / ".render.exr.7-b.tmp.exr").write_bytes(b"new exr")
    (tmp_path / ".render.exr.replacing").write_text(json.dumps(
        {"replace": [[".render.exr.7-b.tmp.png", "render.png"], [".render.exr.7-b.tmp.exr", "render.exr"]]}))
    (tmp_path / ".render.exr.9-c.tmp.exr").write_bytes(b"half of a killed render")
    r = _render(scene, "-o", out)
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    assert snapshot(tmp_path) == {"render.exr": b"new exr", "render.png": b"new png",
                                  "scene.xml": scene.read_bytes()}


def test_a_render_into_a_folder_that_cannot_exist_names_it(tmp_path):
    """-o under a path that cannot be made (a file where a folder is needed): one line naming that path
    (before: 'error: 2', the bare errno of the lock's mkdir)."""
    out, scene, before = _pair(tmp_path)
    r = _render(scene, "-o", tmp_path / "render.exr" / "x.exr")
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    first = r.stderr.strip().splitlines()[0]
    assert f"{tmp_path / 'render.exr'}: File exists" in first, r.stderr     # (mkdir's own reason)
    assert snapshot(tmp_path) == before
