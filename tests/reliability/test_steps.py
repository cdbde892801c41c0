"""Issue 15 defect 10: a second run with nothing changed redoes nothing. mifacerf.steps skips a step by
content digests; ``mifacerf demo`` run again on its own output calls no stage and rewrites no file
(byte-identical, same modification times); a changed input reruns the steps that depend on it."""
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from mifacerf.steps import Steps, digest


def _state(folder: Path):
    return {p.relative_to(folder).as_posix(): (p.read_bytes(), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def test_digest_is_by_content_not_time(tmp_path):
    f = tmp_path / "a.bin"
    f.write_bytes(b"x")
    d = digest(f, {"k": 1})
    os.utime(f, (1, 1))
    assert digest(f, {"k": 1}) == d
    f.write_bytes(b"y")
    assert digest(f, {"k": 1}) != d and digest(tmp_path / "nothing") != digest(tmp_path)
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "model.json").write_text("{}")
    (tmp_path / "m" / "big.npy").write_bytes(b"1")
    m = digest(tmp_path / "m")
    (tmp_path / "m" / "big.npy").write_bytes(b"2")     # a manifest folder digests by its manifest
    assert digest(tmp_path / "m") == m


def test_a_step_runs_once_until_an_input_or_output_changes(tmp_path):
    src, out = tmp_path / "in.txt", tmp_path / "out.txt"
    src.write_text("1")
    calls = []

    def step():
        calls.append(1)
        out.write_text(src.read_text() * 2)
        return {"n": len(calls)}
    assert Steps(tmp_path).run("s", [src], [out], step) == {"n": 1}
    assert Steps(tmp_path).run("s", [src], [out], step) == {"n": 1} and len(calls) == 1
    out.write_text("tampered")
    Steps(tmp_path).run("s", [src], [out], step)
    assert len(calls) == 2
    src.write_text("2")
    Steps(tmp_path).run("s", [src], [out], step)
    assert len(calls) == 3 and out.read_text() == "22"
    (tmp_path / "steps.json").write_text("{ torn")       # a damaged record: the step runs again
    Steps(tmp_path).run("s", [src], [out], step)
    assert len(calls) == 4


def test_demo_second_run_skips_everything_and_rewrites_nothing(tmp_path, monkeypatch):
    from mifacerf import demo

    calls = []

    def fake(name, files, result=None):
        def stage(*a, **k):
            calls.append(name)
            for rel in files:
                p = tmp_path / "out" / rel
                p.parent.mkdir(parents=True, exist_ok=True)
                p.write_text(f"{name} {rel} {len(calls)}")   # a new run makes new content
            return result
        return stage
    monkeypatch.setattr(demo, "stage_capture", fake("capture", ["capture/manifest.json", "capture/hand/h.json",
                                                                "contact_sheet.png"], "x"))
    monkeypatch.setattr(demo, "stage_register", fake("register", ["capture/registration/registration.json"], "x"))
    monkeypatch.setattr(demo, "stage_model", fake("model", ["model/model.json"], "x"))
    monkeypatch.setattr(demo, "stage_renders", fake("renders", ["renders/a.exr", "renders.png"], {"frames": 27}))
    monkeypatch.setattr(demo, "stage_performance", fake("performance", ["performance_render/v.mp4"], {"frames": 9}))
    monkeypatch.setattr(demo, "stage_metrics", fake("metrics", ["metrics_cases.png", "bench/b.png"],
                                                    {"cases": {"summary": {}, "truth_noise_psnr": 40.0},
                                                     "bench": {"results": []}}))
    out = tmp_path / "out"
    r = CliRunner().invoke(demo.demo_cmd, ["-o", str(out), "--preset", "tiny"])
    assert r.exit_code == 0, r.output
    assert calls == ["capture", "register", "model", "renders", "performance", "metrics"]
    before = _state(out)
    r = CliRunner().invoke(demo.demo_cmd, ["-o", str(out), "--preset", "tiny"])
    assert r.exit_code == 0, r.output
    assert len(calls) == 6, calls                     # nothing ran again
    assert _state(out) == before                      # byte-identical, same mtimes (metrics.json, steps.json)
    assert "skipped (inputs and outputs unchanged): capture, register, model, renders, performance, metrics" \
        in r.output
    (out / "capture" / "hand" / "h.json").write_text("a point moved")    # an input of the registration
    CliRunner().invoke(demo.demo_cmd, ["-o", str(out), "--preset", "tiny"])
    assert calls[6:] == ["register", "model", "renders", "performance", "metrics"]


def test_two_demos_on_one_folder_the_second_is_refused_with_exit_3(tmp_path, monkeypatch):
    """A second 'mifacerf demo -o OUT' while one runs is refused at once (exit 3, who holds it named) and
    calls no stage, instead of both rewriting OUT/steps.json; the lock file goes with the run."""
    from mifacerf import demo
    from mifacerf.cli import main
    from mifacerf.errors import EXIT_REFUSED

    from .faults import hold_lock

    calls = []
    for name in ("capture", "register", "model", "renders", "performance", "metrics"):
        monkeypatch.setattr(demo, f"stage_{name}", lambda *a, _n=name, **k: calls.append(_n))
    out = tmp_path / "out"
    release = hold_lock(out, ValueError, ephemeral=True)
    try:
        r = CliRunner().invoke(main, ["demo", "-o", str(out), "--preset", "tiny"])
    finally:
        release()
    assert r.exit_code == EXIT_REFUSED, r.output
    assert "out: locked by PID" in r.stderr and "Traceback" not in r.output
    assert calls == [] and sorted(os.listdir(tmp_path)) == ["out"] and os.listdir(out) == []


def test_sigkill_during_the_demo_steps_leaves_old_or_new_and_the_rerun_redoes_only_what_is_needed(tmp_path):
    """Item 7: the demo (stand-in stages, each output a transaction) killed at random moments of a rerun
    after a hand input changed: every stage's output is its previous complete state or the new one, the
    step record is whole, and the next run completes, calling only the stages whose record does not
    already match (each one it calls changes its record: nothing is redone needlessly); the run after
    calls none."""
    import json
    import random

    from mifacerf.formats.files import repair_if_needed

    from .faults import killed, snapshot, start_child
    from .stand_ins import DEMO_FOLDERS, DEMO_STEPS, run_demo

    out, calls = tmp_path / "out", tmp_path / "calls.log"
    run_demo(str(out), slow=0.0)
    rnd = random.Random(7)
    n_killed = 0
    for version in "bcd":
        before = {rel: snapshot(out / rel) for _, rel, _ in DEMO_FOLDERS}
        (out / "capture" / "hand" / "h.json").write_text(version)
        calls.write_text("")
        p = start_child("demo", {"out": str(out), "slow": 0.08}, f"time:{rnd.uniform(0.1, 2.2):.3f}")
        p.wait(timeout=120)
        p.stdout.read(), p.stderr.read()
        n_killed += killed(p)
        for step, rel, marker in DEMO_FOLDERS:       # the previous complete state, or the new one
            repair_if_needed(out / rel, marker, OSError)
            now = snapshot(out / rel)
            if now != before[rel]:
                assert json.loads(now[marker]) == {"version": version}, (step, now)
                assert sorted(now) == sorted([marker] + [f"f{i}.txt" for i in range(4)]), (step, sorted(now))
                assert all(now[f"f{i}.txt"] == f"{step} {version} {i}".encode() for i in range(4))
        record = json.loads((out / "steps.json").read_text())["steps"]     # whole (written atomically)
        calls.write_text("")
        run_demo(str(out), slow=0.0)
        again = [ln.split()[1] for ln in calls.read_text().splitlines() if ln.startswith("start")]
        after = json.loads((out / "steps.json").read_text())["steps"]
        for step in again:                            # each stage it ran was needed: its record changes
            assert record.get(step, {}).get("inputs") != after[step]["inputs"] or \
                record.get(step, {}).get("outputs") != after[step]["outputs"], (step, again)
        for step in set(DEMO_STEPS[1:]) - set(again):    # what it skipped was done by the killed run
            assert record[step]["inputs"] == after[step]["inputs"], step
        for step, rel, marker in DEMO_FOLDERS:
            assert json.loads((out / rel / marker).read_text()) == {"version": version}
        assert "capture" not in again                  # (its inputs never changed)
        calls.write_text("")
        run_demo(str(out), slow=0.0)
        assert calls.read_text() == ""                 # nothing changed: nothing runs
    assert n_killed >= 2                               # (the kills landed inside the run)
