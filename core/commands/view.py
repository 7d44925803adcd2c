"""``inspect view``: the operator page over a results store, and the live page's start-up for ``inspect run --view``."""
from __future__ import annotations

import time
from pathlib import Path

import click

from core.commands.inspection import fail


def start_view(results: Path, feed, host: str, port: int, token: str | None, jpeg_quality: int, max_fps: float,
               echo=click.echo):
    """Serve the page in a background thread and say where; a port that is taken is a one-line error."""
    from core.view.app import create_app
    from core.view.server import ViewError, ViewServer, exposure_warning

    warning = exposure_warning(host, token)
    if warning:
        click.secho(warning, err=True, fg="yellow", bold=True)
    try:
        server = ViewServer(create_app(results, feed, token=token, jpeg_quality=jpeg_quality, max_fps=max_fps), host, port).start()
    except ViewError as exc:
        fail(str(exc))
    echo(f"operator view: {server.url}{f'?token={token}' if token else ''}")
    return server


def serve_until_interrupted(server) -> None:
    try:
        while True:
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        server.stop()


@click.command("view")
@click.argument("results", type=click.Path(path_type=Path))
@click.option("--host", default="127.0.0.1", show_default=True, help="address to serve on; other than loopback warns")
@click.option("--port", default=8080, show_default=True, type=click.IntRange(1, 65535))
@click.option("--token", default=None, help="require this token (?token=...) from every browser")
def view_command(results: Path, host: str, port: int, token: str | None) -> None:
    """Review a finished run in the browser: filter by verdict and class, page through parts, export CSV."""
    from core.store import db_path

    if not db_path(results).is_file():
        fail(f"{db_path(results)}: no results store here (give the recipe's results.path)")
    if token is not None and len(token) < 8:
        fail("--token: use at least 8 characters")
    server = start_view(results, None, host, port, token, jpeg_quality=85, max_fps=10.0)
    click.echo("Ctrl-C stops serving")
    serve_until_interrupted(server)


def register(cli: click.Group) -> None:
    cli.add_command(view_command)
