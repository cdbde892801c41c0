"""``mifacerf studio CAPTURE``: start the studio's local web server (docs/studio.md)."""
from __future__ import annotations

import click


@click.command("studio")
@click.argument("capture", type=click.Path(file_okay=False, path_type=str))
@click.option("--host", default="127.0.0.1", show_default=True,
              help="address to bind; anything but the loopback address is reachable from other machines (warned)")
@click.option("--port", default=8765, show_default=True, type=click.IntRange(0, 65535), help="port (the next free one if taken)")
@click.option("--strict-port", is_flag=True, help="fail if the port is taken instead of taking the next free one")
def studio_cmd(capture, host, port, strict_port):
    """Point editing and registration of CAPTURE in the browser: open the printed URL."""
    from ..formats.capture import CaptureError
    from .server import serve
    from .session import StudioError

    try:
        serve(capture, host=host, port=port, next_free=not strict_port, echo=click.echo)
    except (CaptureError, StudioError) as exc:
        raise click.ClickException(str(exc).splitlines()[0]) from None
    except KeyboardInterrupt:
        click.echo("stopped")
