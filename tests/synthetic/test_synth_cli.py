"""Bad input to ``mifacerf synth`` / ``truth``: clear errors, nothing half-written that looks complete."""
from click.testing import CliRunner

from mifacerf.cli import main


def test_unknown_preset_is_refused():
    res = CliRunner().invoke(main, ["synth", "/tmp/never-written", "--preset", "huge"])
    assert res.exit_code == 2 and "huge" in res.output


def test_unwritable_output_is_a_clear_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    res = CliRunner().invoke(main, ["synth", str(blocker / "out"), "--preset", "tiny", "--no-contact-sheet"])
    assert res.exit_code == 1
    assert "cannot write the capture here" in res.output
    assert not (blocker.parent / "out").exists()


def test_truth_needs_a_synth_folder(tmp_path):
    res = CliRunner().invoke(main, ["truth", str(tmp_path)])
    assert res.exit_code == 1 and "truth.json" in res.output
