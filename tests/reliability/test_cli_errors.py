"""The command line's top level: one line `mifacerf <command>: error: <message>` for a bad input, the
documented exit codes (mifacerf.errors), a traceback only with --debug or MIFACERF_DEBUG=1."""
import click
import pytest
from click.testing import CliRunner

from mifacerf.cli import main
from mifacerf.errors import (EXIT_CTRL_C, EXIT_ERROR, EXIT_INTERNAL, EXIT_REFUSED, MifacerfError, RefusedError,
                             refused)


def _command(name, exc):
    @click.command(name)
    def cmd():
        raise exc
    return cmd


@pytest.fixture
def extra_command():
    added = []

    def add(name, exc):
        main.add_command(_command(name, exc))
        added.append(name)
    yield add
    for name in added:
        main.commands.pop(name, None)


def one_error_line(result, command):
    err = result.stderr
    assert "Traceback" not in err and "Traceback" not in result.stdout
    lines = [ln for ln in err.splitlines() if ln.startswith(f"mifacerf {command}: error: ")]
    assert len(lines) == 1, err
    return lines[0]


@pytest.mark.parametrize("exc, code", [
    (MifacerfError("capture/manifest.json: missing key 'rig'"), EXIT_ERROR),
    (ValueError("--spp must be > 0"), EXIT_ERROR),
    (FileNotFoundError(2, "No such file or directory", "/x/model.json"), EXIT_ERROR),
    (OSError(28, "No space left on device"), EXIT_ERROR),
    (refused(ValueError, "/x/model: locked by PID 1 on h since now"), EXIT_REFUSED),
    (KeyboardInterrupt(), EXIT_CTRL_C),
    (TypeError("unsupported operand"), EXIT_INTERNAL),
    (click.ClickException("a click error"), 1),
])
def test_errors_are_one_line_with_the_documented_exit_code(extra_command, exc, code):
    extra_command("boom", exc)
    r = CliRunner().invoke(main, ["boom"])
    assert r.exit_code == code, (r.output, r.exception)
    line = one_error_line(r, "boom")
    if isinstance(exc, FileNotFoundError):
        assert line.endswith("/x/model.json: No such file or directory")
    if code == EXIT_INTERNAL:
        assert "internal error: TypeError" in line and "--debug" in r.stderr


def test_debug_shows_the_traceback(extra_command, monkeypatch):
    extra_command("boom", ValueError("bad"))
    r = CliRunner().invoke(main, ["--debug", "boom"])
    assert isinstance(r.exception, ValueError)
    monkeypatch.setenv("MIFACERF_DEBUG", "1")
    r = CliRunner().invoke(main, ["boom"])
    assert isinstance(r.exception, ValueError)


def test_refused_is_both_classes():
    class StageError(ValueError):
        pass
    e = refused(StageError, "locked")
    assert isinstance(e, StageError) and isinstance(e, RefusedError) and str(e) == "locked"
    assert type(refused(StageError, "again")) is type(e)


def test_stage_errors_derive_from_the_base():
    from mifacerf.capture.session import SessionError
    from mifacerf.imageio import ImageFileError
    from mifacerf.registration.register import RegistrationInputError
    from mifacerf.variant import VariantError
    from mifacerf.formats.capture import CaptureError
    from mifacerf.formats.model import ModelError
    from mifacerf.formats.performance import PerformanceError
    from mifacerf.formats.registration import RegistrationError
    for cls in (SessionError, ImageFileError, RegistrationInputError, VariantError):
        assert issubclass(cls, MifacerfError), cls
    for cls in (ModelError, RegistrationError, CaptureError, PerformanceError):   # the folder formats' too
        assert issubclass(cls, MifacerfError) and issubclass(cls, ValueError), cls


def test_a_locked_folder_exits_3_also_through_a_click_error(extra_command, tmp_path):
    """A FolderLock refusal is a RefusedError (exit 3), raised as is or wrapped by a command in a
    click.ClickException (which alone would exit 1)."""
    from mifacerf.formats.files import FolderLock
    from mifacerf.formats.model import ModelError

    folder = tmp_path / "model"

    @click.command("locked")
    @click.option("--wrap", is_flag=True)
    def cmd(wrap):
        try:
            FolderLock(folder, ModelError, wait=False, what="model build").acquire()
        except ModelError as exc:
            if wrap:
                raise click.ClickException(str(exc)) from exc
            raise
    main.add_command(cmd)
    try:
        from .faults import hold_lock

        release = hold_lock(folder, ModelError)
        try:
            for args in ([], ["--wrap"]):
                r = CliRunner().invoke(main, ["locked", *args])
                assert r.exit_code == EXIT_REFUSED, (args, r.output)
                assert "locked by PID" in one_error_line(r, "locked")
        finally:
            release()
    finally:
        main.commands.pop("locked", None)


def test_nested_group_names_the_sub_command(tmp_path):
    (tmp_path / "m").mkdir()
    r = CliRunner().invoke(main, ["evaluate", "render", str(tmp_path), str(tmp_path / "m")])
    assert r.exit_code == 1, r.output
    one_error_line(r, "evaluate render")


def test_warnings_are_one_line(extra_command):
    import warnings

    @click.command("warns")
    def cmd():
        warnings.warn("view far outside the capture cameras")
    main.add_command(cmd)
    try:
        r = CliRunner().invoke(main, ["warns"])
    finally:
        main.commands.pop("warns")
    assert r.exit_code == 0
    assert "mifacerf warns: warning: view far outside the capture cameras" in r.stderr


def test_help_lists_the_exit_codes():
    from mifacerf.cli import EXIT_EPILOG
    from mifacerf.errors import EXIT_CODES
    assert EXIT_EPILOG == "Exit codes (every command): " + "; ".join(f"{c} {m}" for c, m in EXIT_CODES) + "."
    r = CliRunner().invoke(main, ["--help"])
    assert "Exit codes" in r.output and "--debug" in r.output


def test_a_plugin_error_inside_mitsuba_becomes_one_line():
    from mifacerf.rendering.scenefile import SceneError, _plugin_error
    wrapped = RuntimeError('[parser.cpp:1718] At scenes/face_envmap.xml (line 46, col 6): failed to instantiate '
                           'shape plugin of type "facerf_face": Traceback (most recent call last):\n'
                           '    File "plugins/facerf_shape.py", line 73, in __init__\n'
                           "  ModelError: /m/blend.npz: missing (listed in the folder's manifest)")
    e = _plugin_error(wrapped, "scenes/face_envmap.xml")
    assert isinstance(e, SceneError) and isinstance(e, MifacerfError)
    assert str(e).startswith("/m/blend.npz: missing") and "facerf_face" in str(e) and "\n" not in str(e)
    assert _plugin_error(RuntimeError("drjit: out of memory"), "s.xml") is None


def test_a_damaged_proxy_cache_is_recomputed_with_a_warning(tmp_path):
    from types import SimpleNamespace

    from mifacerf.registration.proxies import load_cached, proxy_path
    cap = SimpleNamespace(root=tmp_path)
    path = proxy_path(cap, "neutral", "cam0")
    path.parent.mkdir(parents=True)
    path.write_bytes(b"PK\x03\x04 not a zip at all")
    with pytest.warns(UserWarning, match="damaged cache file.*recomputed"):
        assert load_cached(cap, "neutral", "cam0") is None


def test_build_refuses_an_output_inside_its_inputs(toy_truth):
    for out in (toy_truth, toy_truth / "model", toy_truth / "registration" / "m"):
        r = CliRunner().invoke(main, ["build", str(toy_truth), "-o", str(out)])
        assert r.exit_code == 2 and "the model goes in a folder of its own" in r.output, r.output
    assert not (toy_truth / "model").exists() and not (toy_truth / "registration" / "m").exists()


def test_render_of_a_model_folder_says_how(tmp_path):
    (tmp_path / "model.json").write_text("{}")
    r = CliRunner().invoke(main, ["render", str(tmp_path)])
    assert r.exit_code == 2 and "-D model=" in r.output, r.output


def test_a_stretched_environment_is_refused_like_the_api(tmp_path):
    import numpy as np

    from mifacerf.imageio import write_exr
    from mifacerf.rendering.scenefile import load_scene_file
    write_exr(tmp_path / "wide.exr", np.ones((16, 48, 3), np.float32))
    (tmp_path / "m").mkdir()
    (tmp_path / "m" / "model.json").write_text("{}")
    with pytest.raises(ValueError, match="wide.exr: .*twice as wide as high; got 48x16"):
        load_scene_file("scenes/face_envmap.xml", {"model": str(tmp_path / "m"), "envmap": str(tmp_path / "wide.exr")})
