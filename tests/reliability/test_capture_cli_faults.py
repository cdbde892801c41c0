"""``mifacerf capture`` under faults: options set to 0 or negative are refused (not replaced by the
preset's values), a write failure mid-session stops with the exact resume command, and the command
suggested after a bad port or a failed write is one that runs (issue 15, item 7)."""
import errno
import shlex

import pytest
from click.testing import CliRunner

from mifacerf.capture.session import verify_capture
from mifacerf.cli import main

SMALL = ["--positions", "3", "--strobes", "3", "--resolution", "32", "--expressions", "2", "--motion-sample", "6",
         "--timeout", "0.1"]


def _no_traceback(r):
    assert "Traceback" not in r.output, r.output


@pytest.mark.parametrize("opt, value", [("--positions", "0"), ("--strobes", "0"), ("--resolution", "0"),
                                        ("--expressions", "0"), ("--timeout", "-1"), ("--timeout", "0"),
                                        ("--timeout", "nan"), ("--retries", "-1"), ("--fault-rate", "2"),
                                        ("--max-takes", "0"), ("--motion-sample", "0")])
def test_zero_and_negative_options_are_refused(tmp_path, opt, value):
    r = CliRunner().invoke(main, ["capture", str(tmp_path / "cap"), "--simulate", opt, value])
    assert r.exit_code == 2, r.output
    assert opt in r.output and not (tmp_path / "cap").exists()
    _no_traceback(r)


def _run_hint(output: str):
    line = next(ln for ln in output.splitlines() if "resume with `" in ln)
    words = shlex.split(line.split("resume with `", 1)[1].split("`", 1)[0])
    assert words[:2] == ["mifacerf", "capture"]
    return words[1:]


def test_bad_port_hint_is_a_command_that_runs(tmp_path):
    out = tmp_path / "cap"
    r = CliRunner().invoke(main, ["capture", str(out), "--port", "/dev/ttyNOPE", "--cameras", "gige",
                                  "--preset", "tiny", "--expressions", "1", "--timeout", "0.2"])
    assert r.exit_code == 3, r.output
    args = _run_hint(r.output)
    assert args[args.index("--port") + 1] == "/dev/ttyNOPE" and "--cameras" in args and "--timeout" in args
    r = CliRunner().invoke(main, args)      # the same port is still missing: resumable again, not a usage error
    assert r.exit_code == 3 and "cannot open" in r.output, r.output
    _no_traceback(r)


def test_write_failure_mid_capture_resumes_with_the_hint(tmp_path, monkeypatch):
    from mifacerf.capture import session as S
    from mifacerf.imageio import write_exr

    calls = [0]

    def failing(path, image):
        calls[0] += 1
        if calls[0] == 20:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        write_exr(path, image)
    monkeypatch.setattr(S, "write_exr", failing)
    out = tmp_path / "cap"
    r = CliRunner().invoke(main, ["capture", str(out), "--simulate", *SMALL])
    assert r.exit_code == 3, r.output
    assert "the disk is full" in r.output and "--resume" in r.output
    _no_traceback(r)
    monkeypatch.setattr(S, "write_exr", write_exr)
    r = CliRunner().invoke(main, _run_hint(r.output))
    assert r.exit_code == 0, r.output
    assert verify_capture(out) == (54, [])
