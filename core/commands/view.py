"""``inspect view``: the operator page over a results store, and the live page's start-up for ``inspect run --view``."""
from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

import click

from core.commands.inspection import fail
from core.commands.params import cuda_if_present, demo_recipe

MAX_BENCH_BROWSERS = 64  # each is a thread pulling frames


def start_view(results: Path, feed, host: str, port: int, token: str | None, jpeg_quality: int, max_fps: float,
               echo=click.echo):
    """Serve the page in a background thread and say where; a port that is taken is a one-line error."""
    from core.view.app import create_app
    from core.view.server import ViewError, ViewServer, allowed_hosts, exposure_warning

    warning = exposure_warning(host, token)
    if warning:
        click.secho(warning, err=True, fg="yellow", bold=True)
    try:
        app = create_app(results, feed, token=token, jpeg_quality=jpeg_quality, max_fps=max_fps,
                         allowed_hosts=allowed_hosts(host))
        server = ViewServer(app, host, port).start()
    except ViewError as exc:
        fail(str(exc))
    echo(f"operator view: {server.url}{f'?token={token}' if token else ''}")
    return server


def serve_until_interrupted(server, say: Callable[[], None] = lambda: None) -> None:
    """Serve until Ctrl-C, then stop the server. ``say`` tells the user so, inside the wait: a Ctrl-C right after
    the message must end the serving, not the command."""
    try:
        say()
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
    from core.store import StoreError, db_path, open_readonly

    if not db_path(results).is_file():
        fail(f"{db_path(results)}: no results store here (give the recipe's results.path)")
    try:
        open_readonly(results).close()
    except StoreError as exc:
        fail(str(exc))
    if token is not None and len(token) < 8:
        fail("--token: use at least 8 characters")
    server = start_view(results, None, host, port, token, jpeg_quality=85, max_fps=10.0)
    serve_until_interrupted(server, lambda: click.echo("Ctrl-C stops serving"))


@click.command("bench-view")
@click.argument("recipe", type=click.Path(path_type=Path), default=demo_recipe())
@click.option("--frames", default=40, show_default=True, type=click.IntRange(1), help="parts per configuration")
@click.option("--browsers", default="0,1,3", show_default=True, help="comma-separated numbers of page-like clients")
@click.option("--port", default=None, type=click.IntRange(1, 65535), help="default: a free port")
@click.option("--device", default="cpu", show_default=True, callback=cuda_if_present)
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE")
def bench_view_command(recipe: Path, frames: int, browsers: str, port: int | None, device: str, overrides: tuple[str, ...]) -> None:
    """The loop's frame rate with no browser, with browsers pulling every frame, and with one that stalled.

    The replay runs as fast as it can (rate_fps 0) and loops, so every configuration inspects the same frames.
    """
    import tempfile

    from core.commands.inspection import _load
    from core.view.bench import markdown, run_config
    from drivers.plc_sim import free_port

    try:
        counts = [int(n) for n in browsers.split(",")]
    except ValueError:
        fail(f"--browsers: {browsers!r} is not a comma-separated list of numbers")
    if any(n < 0 for n in counts):
        fail(f"--browsers: {browsers!r}: a number of browsers is 0 or more")
    if max(counts) > MAX_BENCH_BROWSERS:  # a billion threads would fill the memory before the first row
        fail(f"--browsers: {browsers!r}: at most {MAX_BENCH_BROWSERS} browsers at once (the page's viewers on one line, "
             f"not a load test)")

    def label(n: int) -> str:
        return f"{n} browser{'' if n == 1 else 's'}"

    configs = [(label(n), n, False) for n in counts]
    configs.append((f"{label(max(counts))} + 1 stalled", max(counts), True))
    # Benchmark parts must not land in the line's results store or reach its PLC.
    with tempfile.TemporaryDirectory() as tmp:
        loaded = _load(recipe, ("camera.settings.rate_fps=0", "camera.settings.loop=true", f"results.path={tmp}/results",
                                f"outputs=[{{plugin: log, settings: {{file: {tmp}/rejects.log}}}}]", *overrides))
        rows = []
        for name, n, stalled in configs:
            rows.append(run_config(loaded, name, n, stalled, frames, "127.0.0.1", port or free_port(), device))
            click.echo(f"{name}: {rows[-1].fps:.2f} frames/s")
    click.echo(markdown(rows))


def register(cli: click.Group) -> None:
    cli.add_command(view_command)
    cli.add_command(bench_view_command)
