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
