"""The ``mifacerf`` command line.

Commands live next to the code they drive and are imported only when used, so
``mifacerf --help`` stays fast (it imports neither Mitsuba nor any stage):
:data:`LAZY_COMMANDS` maps a command name to ``"module:attribute"`` and the
summary the command list shows (the first sentence of the command's help;
``tests/test_package_root.py`` checks that they agree).
"""
from __future__ import annotations

import importlib
import math
import os
import warnings

import click

#: name → ("module:attribute", summary shown by ``mifacerf --help``)
LAZY_COMMANDS = {
    "synth": ("mifacerf.synthetic.cli:synth_cmd",
              "Render the light-stage capture of a synthetic subject into OUT/capture (truth: OUT/truth)."),
    "truth": ("mifacerf.synthetic.cli:truth_cmd",
              "Path-trace the synthetic subject of OUT (any expression, camera, environment) with alpha."),
    "preview": ("mifacerf.synthetic.preview:preview_cmd",
                "Look at the synthetic subject: a contact sheet of its expressions (no capture needed)."),
    "build": ("mifacerf.rendering.cli:build_cmd",
              "Assemble the relightable morphable model from a registered capture."),
    "render": ("mifacerf.rendering.cli:render_cmd",
               "Render a scene file (scenes/*.xml) that uses mifacerf's plugins."),
    "compress": ("mifacerf.rendering.cli:compress_cmd",
                 "Add PCA-compressed versions of every reflectance field to a model."),
    "bench": ("mifacerf.evaluation.cli:bench_cmd",
              "Benchmark run time per frame against error: dense reference, exact path, compressed ranks."),
    "evaluate": ("mifacerf.evaluation.cli:evaluate_group",
                 "Compare a stage's output with the synthetic ground truth (evaluation only: no stage reads "
                 "the truth)."),
    "demo": ("mifacerf.demo:demo_cmd",
             "Run the main job on the embedded synthetic subject: capture, registration, model, renders, "
             "performance, metrics."),
    "track": ("mifacerf.tracking.cli:track_cmd",
              "Track the dots of a multi-view PERFORMANCE; write the per-frame target mesh (paper §6.4)."),
    "drive": ("mifacerf.tracking.cli:drive_cmd",
              "Drive MODEL with a TRACK: §5 weights per frame, relit renders, composites, a video (paper §7)."),
    "register": ("mifacerf.registration.cli:register_cmd",
                 "Register every expression of CAPTURE into the template (reads only CAPTURE: manifest, "
                 "images, hand/)."),
    "capture": ("mifacerf.capture.cli:capture_cmd",
                "Run a light-stage capture session into the folder OUT (paper §2.1)."),
    "calibrate": ("mifacerf.capture.cli:calibrate_group",
                  "Geometric (Zhang) and radiometric (response, colour) calibration of the cameras (paper §2.1)."),
    "verify": ("mifacerf.formats.cli:verify_cmd",
               "Check every file of a capture, registration, model or performance folder against its manifest."),
    "studio": ("mifacerf.studio.cli:studio_cmd",
               "Point editing and registration of CAPTURE in the browser: open the printed URL."),
}


def load_command(name: str) -> click.Command:
    """Import the module of lazy command ``name`` and return the command (its values checked: :func:`harden`)."""
    module, attr = LAZY_COMMANDS[name][0].split(":")
    return harden(getattr(importlib.import_module(module), attr))


_checked_types: dict[type, type] = {}


def _checked_type(cls: type) -> type:
    """A subclass of click type ``cls`` whose values must be finite (numbers) or non-empty (text, paths)."""
    if cls not in _checked_types:
        number = issubclass(cls, (click.types.FloatParamType, click.types.IntParamType))

        def convert(self, value, param, ctx):
            if isinstance(value, str) and not value.strip():
                self.fail("must not be empty", param, ctx)
            rv = super(checked, self).convert(value, param, ctx)
            if number and isinstance(rv, float) and not math.isfinite(rv):
                self.fail(f"{value!r} is not a finite number", param, ctx)
            return rv
        checked = type(cls.__name__, (cls,), {"convert": convert, "__module__": cls.__module__})
        _checked_types[cls] = checked
    return _checked_types[cls]


def harden(command: click.Command) -> click.Command:
    """Every number option of ``command`` (and of its sub-commands) refuses NaN and ±inf, every text or
    path value refuses the empty string (``-o ""`` would be the working directory): a usage error (exit 2)
    naming the option. Ranges (zero, negative) are each option's own ``click.IntRange``/``FloatRange``."""
    if getattr(command, "_mifacerf_hardened", False):
        return command
    for param in command.params:
        t = param.type
        if type(t) in _checked_types.values():
            continue
        if isinstance(t, (click.types.FloatParamType, click.types.IntParamType, click.types.StringParamType,
                          click.Path)):
            t.__class__ = _checked_type(type(t))
    for sub in getattr(command, "commands", {}).values():
        harden(sub)
    command._mifacerf_hardened = True
    return command


class LazyGroup(click.Group):
    """A click group whose sub-commands are imported on first use; its help lists them without importing."""

    def list_commands(self, ctx):
        return sorted(set(super().list_commands(ctx)) | set(LAZY_COMMANDS))

    def get_command(self, ctx, name):
        if name in LAZY_COMMANDS:
            return load_command(name)
        return super().get_command(ctx, name)

    def parse_args(self, ctx, args):
        ctx.meta.setdefault("mifacerf.argv", list(args))
        return super().parse_args(ctx, args)

    def command_path(self, ctx) -> str:
        """``mifacerf <command> [<sub-command>]`` of this invocation (for one-line error messages)."""
        words, cmd = ["mifacerf"], self
        for arg in ctx.meta.get("mifacerf.argv", []):
            if arg.startswith("-") or not isinstance(cmd, click.Group):
                continue
            try:
                sub = cmd.get_command(ctx, arg)
            except Exception:  # noqa: BLE001 (a command that cannot be imported: its name is enough)
                sub = None
            if sub is None:
                continue
            words.append(arg)
            cmd = sub
        return " ".join(words)

    def invoke(self, ctx):
        """Run the command; an error reaching here is printed as one line (a traceback only with --debug).

        ``mifacerf <command>: error: <message>`` on stderr, exit code by :func:`mifacerf.errors.exit_code_of`
        (docs/reliability.md); click's usage errors keep click's own message (exit 2). Python warnings
        are printed as ``mifacerf <command>: warning: <message>``.
        """
        from .errors import EXIT_REFUSED, RefusedError, exit_code_of, message_of

        debug = bool(ctx.params.get("debug")) or os.environ.get("MIFACERF_DEBUG", "") not in ("", "0")
        with warnings.catch_warnings():
            if not debug:
                warnings.showwarning = lambda message, category, *a, **k: click.echo(
                    f"{self.command_path(ctx)}: warning: {message}", err=True)
            try:
                return super().invoke(ctx)
            except (click.exceptions.Exit, click.Abort, click.UsageError):
                raise
            except click.ClickException as exc:
                if debug:
                    raise
                # a lock refusal a command wrapped in its click error still exits 3 (not click's 1)
                self._fail(ctx, exc.format_message(),
                           EXIT_REFUSED if isinstance(exc.__cause__, RefusedError) else exc.exit_code)
            except (Exception, KeyboardInterrupt) as exc:  # noqa: BLE001 (the top of the program)
                if debug:
                    raise
                self._fail(ctx, message_of(exc) if not isinstance(exc, KeyboardInterrupt) else "interrupted",
                           exit_code_of(exc))

    def _fail(self, ctx, message: str, code: int):
        first, *rest = message.splitlines() or [""]
        click.echo(f"{self.command_path(ctx)}: error: {first}", err=True)
        for line in rest:
            click.echo(f"  {line}" if line.strip() else line, err=True)
        if code >= 4 and code != 130:
            click.echo("  (rerun with --debug, or MIFACERF_DEBUG=1, for the traceback)", err=True)
        ctx.exit(code if code else 1)

    def format_commands(self, ctx, formatter):
        """The command list, lazy commands by their :data:`LAZY_COMMANDS` summary (click's layout)."""
        commands = []
        for name in self.list_commands(ctx):
            if name in LAZY_COMMANDS:
                commands.append((name, click.Command(name, help=LAZY_COMMANDS[name][1])))
            elif not self.commands[name].hidden:
                commands.append((name, self.commands[name]))
        if commands:
            limit = formatter.width - 6 - max(len(name) for name, _ in commands)
            with formatter.section("Commands"):
                formatter.write_dl([(name, cmd.get_short_help_str(limit)) for name, cmd in commands])


#: the exit codes of every command: mifacerf.errors.EXIT_CODES written out (``mifacerf --help`` imports no
#: module but this one; tests/reliability/test_cli_errors.py checks that the two agree)
EXIT_EPILOG = ("Exit codes (every command): 0 done; 1 bad input or file, or a failed step (one line naming it); "
               "2 bad usage: unknown option, bad option value, missing argument; 3 refused or interrupted, nothing "
               "lost: folder locked by another run, or a capture session to resume; 4 internal error (a bug): "
               "rerun with --debug for the traceback; 130 interrupted by Ctrl-C.")


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]}, epilog=EXIT_EPILOG)
@click.version_option(package_name="mifacerf")
@click.option("--debug", is_flag=True, help="Show the traceback of an error (also MIFACERF_DEBUG=1).")
def main(debug):
    """Animatable, relightable facial reflectance fields on Mitsuba 3.

    The pipeline: synth (or capture) → register → build → render; demo runs it all.
    An error prints one line, `mifacerf COMMAND: error: ...`, naming the file or option.
    """
