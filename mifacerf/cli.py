"""The ``mifacerf`` command line.

Commands live next to the code they drive and are imported only when used, so
``mifacerf --help`` stays fast: :data:`LAZY_COMMANDS` maps a command name to
``"module:attribute"``.
"""
from __future__ import annotations

import importlib

import click

LAZY_COMMANDS = {
    "synth": "mifacerf.synthetic.cli:synth_cmd",
    "truth": "mifacerf.synthetic.cli:truth_cmd",
    "build": "mifacerf.rendering.cli:build_cmd",
    "render": "mifacerf.rendering.cli:render_cmd",
    "compress": "mifacerf.rendering.cli:compress_cmd",
    "bench": "mifacerf.evaluation.cli:bench_cmd",
    "evaluate": "mifacerf.evaluation.cli:evaluate_group",
    "demo": "mifacerf.demo:demo_cmd",
    "track": "mifacerf.tracking.cli:track_cmd",
    "drive": "mifacerf.tracking.cli:drive_cmd",
    "register": "mifacerf.registration.cli:register_cmd",
    "capture": "mifacerf.capture.cli:capture_cmd",
    "calibrate": "mifacerf.capture.cli:calibrate_group",
    "studio": "mifacerf.studio.cli:studio_cmd",
}


class LazyGroup(click.Group):
    """A click group whose sub-commands are imported on first use."""

    def list_commands(self, ctx):
        return sorted(set(super().list_commands(ctx)) | set(LAZY_COMMANDS))

    def get_command(self, ctx, name):
        if name in LAZY_COMMANDS:
            module, attr = LAZY_COMMANDS[name].split(":")
            return getattr(importlib.import_module(module), attr)
        return super().get_command(ctx, name)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mifacerf")
def main():
    """Animatable, relightable facial reflectance fields on Mitsuba 3.

    The pipeline: synth (or capture) → register → build → render; demo runs it all.
    """
