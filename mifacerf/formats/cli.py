"""CLI: ``mifacerf verify FOLDER`` — the full integrity check of a capture, registration, model or
performance folder (every listed file's size and sha256).

Exit codes: 0 every file verifies; 1 problems found (one line each, naming the file); 2 not a folder
of a known format, or one that cannot be opened (the message says why).
"""
from __future__ import annotations

import json
from pathlib import Path

import click


def folder_kind(folder: Path) -> str | None:
    """"model", "registration", "capture", "performance" or None, from the folder's manifest file."""
    if (folder / "model.json").exists():
        return "model"
    if (folder / "registration.json").exists():
        return "registration"
    mpath = folder / "manifest.json"
    if mpath.exists():
        try:
            fmt = json.loads(mpath.read_text()).get("format")
        except (ValueError, AttributeError, UnicodeDecodeError):
            return "capture"         # let the capture reader name the problem
        return "performance" if fmt == "mifacerf.performance" else "capture"
    return None


def verify_folder(folder: str | Path) -> tuple[str, list[str]]:
    """(kind, problems) of ``folder``; raises ValueError (the formats' errors) when it cannot be opened."""
    folder = Path(folder)
    kind = folder_kind(folder)
    if kind == "model":
        from .model import ModelFolder

        return kind, ModelFolder(folder).verify()
    if kind == "registration":
        from .registration import Registration

        return kind, Registration(folder).verify()
    if kind == "capture":
        from .capture import Capture

        return kind, Capture(folder).verify()
    if kind == "performance":
        from .performance import PerformanceFolder

        return kind, PerformanceFolder(folder).verify()
    raise ValueError(f"{folder}: no model.json, registration.json or manifest.json: not a mifacerf folder")


@click.command("verify")
@click.argument("folder", type=click.Path(exists=True, file_okay=False))
def verify_cmd(folder):
    """Check every file of a capture, registration, model or performance folder against its manifest.

    Every file FOLDER's manifest lists is checked for its size and sha256. Exit 0: all verify; 1: problems
    (one line each, naming the file); 2: not a folder that can be opened."""
    try:
        kind, problems = verify_folder(folder)
    except ValueError as exc:
        click.echo(f"Error: {exc}", err=True)
        raise SystemExit(2) from None
    for p in problems:
        click.echo(p)
    if problems:
        click.echo(f"{folder}: {len(problems)} problem(s) in this {kind} folder", err=True)
        raise SystemExit(1)
    click.echo(f"{folder}: every file of this {kind} folder verifies")
