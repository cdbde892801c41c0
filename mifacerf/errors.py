"""The project's error classes' common base and the command line's exit codes (ground floor).

Every stage raises its own error class for a bad input (``CaptureError``, ``RegistrationInputError``,
``ModelError``, ``ImageFileError``, ``VariantError``, ...); each derives from :class:`MifacerfError`
(and keeps its historical base, ``ValueError``, ``OSError`` or ``RuntimeError``, so existing
``except`` clauses still catch it). The message names the file or option and says what is wrong, on
its first line: the command line (``mifacerf.cli``) prints that line as
``mifacerf <command>: error: <message>`` without a traceback (``mifacerf --debug ...`` or
``MIFACERF_DEBUG=1`` shows the traceback).

:class:`RefusedError` is a refusal that lost nothing and may simply be retried: a folder locked by
another running process, a session interrupted that resumes. :func:`refused` makes one out of a
stage's own error class (an instance of both), so that ``except ModelError`` still catches it.

Exit codes of every ``mifacerf`` command (docs/reliability.md):

====  ==========================================================================================
0     done
1     error: a bad input, a file that cannot be read or written, a step that failed (one line)
2     usage: an unknown option, a bad option value, a missing argument (click's own message)
3     refused or interrupted, nothing lost: the folder is locked by another run, or (capture) the
      session stopped and resumes with the printed command
4     internal error (a bug): one line; rerun with ``--debug`` for the traceback and report it
130   interrupted by Ctrl-C
====  ==========================================================================================
"""
from __future__ import annotations

EXIT_OK = 0
EXIT_ERROR = 1
EXIT_USAGE = 2
EXIT_REFUSED = 3
EXIT_INTERNAL = 4
EXIT_CTRL_C = 130

#: (code, meaning) for help epilogs and docs
EXIT_CODES = (
    (EXIT_OK, "done"),
    (EXIT_ERROR, "bad input or file, or a failed step (one line naming it)"),
    (EXIT_USAGE, "bad usage: unknown option, bad option value, missing argument"),
    (EXIT_REFUSED, "refused or interrupted, nothing lost: folder locked by another run, or a capture "
                   "session to resume"),
    (EXIT_INTERNAL, "internal error (a bug): rerun with --debug for the traceback"),
    (EXIT_CTRL_C, "interrupted by Ctrl-C"),
)


class MifacerfError(Exception):
    """Base of every mifacerf error caused by an input (a file, an option, a folder's state)."""

    exit_code = EXIT_ERROR


class RefusedError(MifacerfError):
    """Refused or interrupted without losing anything; retrying later (or resuming) is the answer."""

    exit_code = EXIT_REFUSED


_refused_classes: dict[type, type] = {}


def refused(error: type[BaseException], message: str) -> BaseException:
    """An exception that is both ``error`` (a stage's class) and :class:`RefusedError`."""
    if issubclass(error, RefusedError):
        return error(message)
    cls = _refused_classes.get(error)
    if cls is None:
        cls = _refused_classes[error] = type(f"Refused{error.__name__}", (error, RefusedError), {})
    return cls(message)


def exit_code_of(exc: BaseException) -> int:
    """The exit code for an exception reaching the top of a command (see the table above)."""
    if isinstance(exc, KeyboardInterrupt):
        return EXIT_CTRL_C
    if isinstance(exc, MifacerfError):
        return exc.exit_code
    if isinstance(exc, (ValueError, OSError)):
        return EXIT_ERROR
    return EXIT_INTERNAL


def message_of(exc: BaseException) -> str:
    """A one-line-first message for ``exc``: an OSError as ``<file>: <reason>``, else its text."""
    if isinstance(exc, OSError) and not isinstance(exc, MifacerfError) and exc.strerror:
        where = exc.filename if exc.filename is not None else None
        text = f"{where}: {exc.strerror}" if where is not None else exc.strerror
        if exc.filename2 is not None:
            text = f"{where} -> {exc.filename2}: {exc.strerror}"
        return text
    text = str(exc).strip()
    if isinstance(exc, KeyError) and exc.args:
        text = f"missing key {exc.args[0]!r}"
    if exit_code_of(exc) == EXIT_INTERNAL:
        text = f"internal error: {type(exc).__name__}: {text or '(no message)'}"
    return text or type(exc).__name__
