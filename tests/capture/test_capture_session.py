"""Capture sessions against the simulated lab: complete folders, faults, motion, interruption,
resume, full disks, silent controllers, tampered files. Nothing captured may ever be lost."""
import errno
import json
import re

import numpy as np
import pytest

from helpers.capture import new_session, run_lab, tiny_rig
from mifacerf.capture.journal import read_journal
from mifacerf.capture.session import CaptureSession, SessionError, SessionInterrupted, verify_capture
from mifacerf.capture.simulation.lab import LabOptions
from mifacerf.formats.capture import Capture
from mifacerf.formats.files import sha256_file


def files_with_sha(root):
    """{relative path: sha256} of every image under root (takes/, images/, quarantine/)."""
    return {p.relative_to(root).as_posix(): sha256_file(p) for p in root.rglob("*.exr")}


def assert_preserved(before, after):
    """Every file of ``before`` is in ``after`` with the same content, where it was or promoted to images/."""
    for p, sha in before.items():
        promoted = re.sub(r"^takes/([^/]+)/t\d+/", r"images/\1/", p)
        assert after.get(p) == sha or after.get(promoted) == sha, p


def events(root, name):
    return [r for r in read_journal(root / "session.jsonl").records if r["event"] == name]


def assert_complete(root, session):
    n = len(session.expressions) * len(session.rig.cameras) * len(session.rig.lights)
    ok, problems = verify_capture(root)
    assert problems == [] and ok == n
    cap = Capture(root)
    assert len(cap.checksums) == n
    assert not list(root.rglob("*.tmp*"))  # no temporary files left behind


def test_clean_session_writes_a_complete_verified_capture(tmp_path, rig):
    s = new_session(tmp_path / "cap", rig, 2)
    rep, lab = run_lab(s)
    assert rep.complete and rep.expressions_complete == 2
    assert_complete(tmp_path / "cap", s)
    # the images are what the cameras recorded: the renderer's radiance times the light's irradiance
    cap = Capture(tmp_path / "cap")
    cam = rig.cameras[1]
    params = lab.subject.expressions["smile"]
    truth = lab.renderer.render(params, cam, np.array([5]))[0] * rig.lights.irradiance[5]
    np.testing.assert_allclose(cap.raw_image("smile", cam.name, 5), truth, atol=2e-3, rtol=2e-3)
    # the first expression was taken twice (motion reference); the spare take is kept, not deleted
    assert rep.takes == 3
    final = {(r["expression"], r["take"]): r["status"] for r in events(tmp_path / "cap", "take_end")}
    assert sorted(final.values()) == ["accepted", "accepted", "rejected"]
    assert sorted(p.name for p in (tmp_path / "cap" / "takes" / "neutral").iterdir()) == ["t02"]


def test_faults_cost_retries_not_data(tmp_path, rig):
    s = new_session(tmp_path / "cap", rig, 3)
    rep, lab = run_lab(s, LabOptions(fault_rate=0.08, frame_drop=0.02, seed=4))
    assert rep.complete
    assert_complete(tmp_path / "cap", s)
    assert rep.refire_runs > 0 and rep.frames_missing + rep.misfires > 0
    assert rep.link["retries"] > 0
    counts = lab.device.counts
    assert counts.dropped + counts.garbled > 0 and counts.misfires + counts.resets > 0


def test_blurred_take_is_repeated_and_kept(tmp_path, rig):
    s = new_session(tmp_path / "cap", rig, 3)
    rep, lab = run_lab(s, LabOptions(force_motion=[["smile", 1]], motion_mm=12.0))
    root = tmp_path / "cap"
    assert rep.complete and rep.takes_blurred == 1 and rep.takes_moved == rep.moved_and_caught == 1
    rejected = [r for r in events(root, "take_end") if r["status"] == "rejected" and r["expression"] == "smile"]
    assert len(rejected) == 1 and rejected[0]["take"] == 1 and "motion" in rejected[0]["reason"]
    verdicts = {(r["expression"], r["take"]): r for r in events(root, "motion")}
    assert verdicts[("smile", 1)]["blurred"] and not verdicts[("smile", 2)]["blurred"]
    assert not verdicts[("big_smile", 1)]["blurred"]
    # the blurred take's frames are still on disk, untouched
    kept = list((root / "takes" / "smile" / "t01").rglob("*.exr"))
    assert len(kept) == len(rig.cameras) * len(rig.lights)
    assert_complete(root, s)


def test_interrupted_session_resumes_exactly_where_it_stopped(tmp_path, rig):
    root = tmp_path / "cap"
    s = new_session(root, rig, 3)
    n_per_take = len(rig.cameras) * len(rig.lights)
    written = []

    def hook(session, lab):
        inner = session.write_image

        def write(path, image):
            if len(written) == n_per_take + 10:  # in the middle of the second take of "neutral"
                raise KeyboardInterrupt
            inner(path, image)
            written.append(path)
        session.write_image = write

    with pytest.raises(SessionInterrupted, match="--resume"):
        run_lab(s, hook=hook)
    before = files_with_sha(root)
    assert len(before) == len(written) > 0
    assert not (root / "manifest.json").exists()
    assert events(root, "interrupted")[-1]["reason"].startswith("stopped by the operator")

    s2 = CaptureSession.open(root)
    rep, _ = run_lab(s2)
    assert rep.complete and rep.resumes == 1
    after = files_with_sha(root)
    # every frame written before the interruption still exists, byte for byte (maybe moved to images/)
    assert_preserved(before, after)
    # the resumed take fired only the lights still missing
    runs = [r for r in events(root, "run") if r["expression"] == "neutral" and r["take"] == 2]
    assert runs[-1]["lights"] != "all" and len(runs[-1]["lights"]) < len(rig.lights)
    assert_complete(root, s2)


def test_frames_written_but_not_journaled_are_adopted(tmp_path, rig):
    root = tmp_path / "cap"
    s = new_session(root, rig, 1)

    def hook(session, lab):
        real_log = session._log

        def log(event, **data):
            if event == "frames":  # the process dies between the rename and the journal line
                raise KeyboardInterrupt
            return real_log(event, **data)
        session._log = log

    with pytest.raises(SessionInterrupted):
        run_lab(s, hook=hook)
    on_disk = files_with_sha(root)
    assert on_disk and not events(root, "frames")
    rep, _ = run_lab(CaptureSession.open(root))
    adopted = {(r["camera"], l): sha for r in events(root, "adopted") for l, sha in r["frames"]}
    assert len(adopted) == len(on_disk)
    assert rep.complete
    assert_complete(root, s)


def test_full_disk_interrupts_cleanly_and_resumes(tmp_path, rig):
    root = tmp_path / "cap"
    s = new_session(root, rig, 2)
    calls = [0]

    def hook(session, lab):
        inner = session.write_image

        def write(path, image):
            calls[0] += 1
            if calls[0] > 20:
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
            inner(path, image)
        session.write_image = write

    with pytest.raises(SessionInterrupted, match="disk is full.*--resume") as e:
        run_lab(s, hook=hook)
    assert "free some space" in str(e.value)
    assert events(root, "interrupted")[-1]["errno"] == errno.ENOSPC
    kept = files_with_sha(root)
    assert len(kept) == 20 and not list(root.rglob("*.tmp*"))
    rep, _ = run_lab(CaptureSession.open(root))
    assert rep.complete
    assert_preserved(kept, files_with_sha(root))
    assert_complete(root, s)


def test_silent_controller_leaves_a_resumable_session(tmp_path, rig):
    root = tmp_path / "cap"
    s = new_session(root, rig, 2)

    def hook(session, lab):
        lab.device.faults.silent_after = 4  # the controller hangs part-way through the session

    with pytest.raises(SessionInterrupted, match="stopped answering|does not answer"):
        run_lab(s, hook=hook, timeout=0.02, retries=1)
    rep, _ = run_lab(CaptureSession.open(root))
    assert rep.complete and rep.interruptions == 1
    assert_complete(root, s)


def test_a_take_with_a_missing_frame_is_never_complete(tmp_path, rig):
    root = tmp_path / "cap"
    s = new_session(root, rig, 1, max_runs=3)

    def hook(session, lab):
        lab.device.faults.dead_strobes = (6,)  # one strobe never fires

    with pytest.raises(SessionInterrupted, match=r"lights \[6\].*check those strobes"):
        run_lab(s, hook=hook)
    assert not events(root, "expression_complete") and not (root / "manifest.json").exists()
    assert not [r for r in events(root, "take_end") if r["status"] in ("accepted", "candidate")]
    rep, _ = run_lab(CaptureSession.open(root))  # strobe repaired: the open takes are filled in
    assert rep.complete
    assert_complete(root, s)


def test_tampered_files_are_quarantined_and_recaptured(tmp_path, rig):
    root = tmp_path / "cap"
    s = new_session(root, rig, 2)
    rep, _ = run_lab(s)
    (root / "manifest.json").unlink()  # pretend the session died before the manifest
    victim = root / "images" / "smile" / rig.cameras[0].name / "L003.exr"
    data = bytearray(victim.read_bytes())
    data[-5] ^= 0xFF
    victim.write_bytes(bytes(data))
    s2 = CaptureSession.open(root)
    s2.state.finished = False
    rep, _ = run_lab(s2)
    assert rep.complete
    bad = events(root, "expression_invalid")
    assert [b["expression"] for b in bad] == ["smile"]
    quarantined = list((root / "quarantine").rglob("L003.exr"))
    assert quarantined and quarantined[0].read_bytes() == bytes(data)  # kept, not deleted
    assert_complete(root, s)


def test_refuses_to_overwrite_a_session_or_a_capture(tmp_path, rig):
    root = tmp_path / "cap"
    s = new_session(root, rig, 1)
    with pytest.raises(SessionError, match="already holds a capture session"):
        new_session(root, rig, 1)
    run_lab(s)
    (root / "session.jsonl").rename(root / "old.jsonl")
    with pytest.raises(SessionError, match="complete capture"):
        new_session(root, rig, 1)
    with pytest.raises(SessionError, match="no capture session to resume|without a session journal"):
        CaptureSession.open(root)
    with pytest.raises(SessionError, match="no capture session"):
        CaptureSession.open(tmp_path / "nothing")


def test_session_over_a_pseudo_terminal(tmp_path):
    rig = tiny_rig(3, 3, 2, 32)
    s = new_session(tmp_path / "cap", rig, 2)
    rep, lab = run_lab(s, LabOptions(fault_rate=0.03, seed=2), pty=True, timeout=0.1)
    assert rep.complete
    assert_complete(tmp_path / "cap", s)


def test_journal_records_what_is_needed_to_resume(tmp_path, rig):
    root = tmp_path / "cap"
    s = new_session(root, rig, 1)
    run_lab(s)
    recs = read_journal(root / "session.jsonl").records
    plan = recs[0]
    assert plan["event"] == "plan" and plan["format"] == "mifacerf.capture-session"
    assert len(plan["rig"]["lights"]["lights"]) == len(rig.lights)
    frames = [r for r in recs if r["event"] == "frames"]
    for r in frames:
        for light, sha in r["frames"]:
            assert len(sha) == 64
    complete = [r for r in recs if r["event"] == "expression_complete"][0]
    manifest = json.loads((root / "manifest.json").read_text())
    assert complete["checksums"] == {k: v for k, v in manifest["checksums"].items()}
    assert manifest["session"]["journal"] == "session.jsonl"


def test_a_second_session_on_one_folder_is_refused_while_the_first_runs(tmp_path, rig):
    """Two sessions on one folder would interleave their takes in one journal: while one runs (holds the
    folder's lock), another is refused at once with a RefusedError naming the holder; nothing is written."""
    import threading

    from mifacerf.errors import RefusedError
    from mifacerf.formats.files import FolderLock

    root = tmp_path / "cap"
    s = new_session(root, rig, 2)
    before = sorted(p.relative_to(root).as_posix() for p in root.rglob("*"))
    held, done = threading.Event(), threading.Event()

    def hold():                       # another thread's descriptor is another holder, as a process would be
        with FolderLock(root, SessionError):
            held.set()
            done.wait(60)
    t = threading.Thread(target=hold)
    t.start()
    try:
        assert held.wait(30)
        with pytest.raises(SessionError, match=r"locked by PID \d+ .*another capture session is running") as exc:
            run_lab(s)
        assert isinstance(exc.value, RefusedError)
    finally:
        done.set()
        t.join()
    assert sorted(p.relative_to(root).as_posix() for p in root.rglob("*")) == before
    rep, _ = run_lab(CaptureSession.open(root))       # once the holder is gone the session runs
    assert rep.complete
