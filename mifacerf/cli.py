"""The ``mifacerf`` command line. Sub-commands import their modules lazily."""
from __future__ import annotations

import click


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mifacerf")
def main():
    """Animatable, relightable facial reflectance fields on Mitsuba 3."""


if __name__ == "__main__":
    main()
from mifacerf.capture.cli import capture_cmd, calibrate_group  # noqa: E402
main.add_command(capture_cmd); main.add_command(calibrate_group)  # noqa: E702
