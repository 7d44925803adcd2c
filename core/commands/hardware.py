"""``inspect plc-sim`` (a Modbus PLC stand-in) and ``inspect camera record`` (build a test set from the line).

Drivers and plugins are imported inside the commands so that ``inspect --help`` stays fast.
"""
from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import click

from core.commands.params import Finite, make_folder
from drivers.serial_line import MAX_BAUDRATE


def _fail(message: str) -> None:
    click.echo(f"error: {message}", err=True)
    raise click.exceptions.Exit(2)


@click.command("plc-sim")
@click.option("--host", default="127.0.0.1", show_default=True, help="address to listen on (0.0.0.0: every interface)")
@click.option("--port", type=click.IntRange(0, 65535), default=5020, show_default=True, help="Modbus TCP port; 0: no TCP")
@click.option("--rtu", "rtu", metavar="PATH", default=None, help="also serve Modbus RTU on this serial port (e.g. /dev/pts/3)")
@click.option("--baudrate", type=click.IntRange(1, MAX_BAUDRATE), default=19200, show_default=True, help="RTU baud rate")
@click.option("--delay-ms", type=Finite(0), default=0.0, help="answer every request this late (fault testing)")
@click.option("--duration", type=Finite(0), default=None, help="stop after this many seconds (default: until Ctrl-C)")
def plc_sim_command(host: str, port: int, rtu: str | None, baudrate: int, delay_ms: float, duration: float | None) -> None:
    """Stand in for the conveyor PLC: a Modbus server that prints every coil or register change."""
    from drivers import plc_sim

    if port == 0 and not rtu:
        _fail("--port 0 turns TCP off; give --rtu PATH then")

    def show(line: str) -> None:
        click.echo(line)
        sys.stdout.flush()

    options = {"baudrate": baudrate, "delay_s": delay_ms / 1000.0}
    try:
        if port:
            sim = plc_sim.serve_in_thread(host, port, on_change=show, rtu=rtu, **options)
        else:
            sim = plc_sim.serve_rtu_in_thread(rtu, on_change=show, **options)
    except (OSError, RuntimeError) as exc:
        _fail(str(exc))
    click.echo(f"{plc_sim.stamp()} PLC simulator on {sim.label}, every unit id; coils and registers 0..{plc_sim.SIZE - 1}"
               + (" (Ctrl-C to stop)" if duration is None else f" for {duration:g} s"))
    sys.stdout.flush()
    try:
        end = None if duration is None else time.monotonic() + duration
        while end is None or time.monotonic() < end:
            time.sleep(0.2 if end is None else max(0.0, min(0.2, end - time.monotonic())))
    except KeyboardInterrupt:
        pass
    finally:
        sim.stop()
    click.echo(f"{plc_sim.stamp()} PLC simulator stopped ({len(sim.writes)} writes received)")


@click.command("record")
@click.argument("recipe", type=click.Path(path_type=Path))
@click.argument("out", type=click.Path(path_type=Path))
@click.option("--frames", "count", type=click.IntRange(1), required=True, help="number of rectified pairs to record")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE", help="override a recipe value (repeatable)")
@click.option("--max-errors", type=click.IntRange(1), default=50, show_default=True, help="give up after this many missed frames in a row")
@click.option("--every", "every_s", type=click.FloatRange(0.0), default=0.0, show_default=True,
              help="seconds between the pairs recorded, by the camera's capture stamps (the frames between are read "
                   "and let go): a repeatability study spread over a shift")
def record_command(recipe: Path, out: Path, count: int, overrides: tuple[str, ...], max_errors: int,
                   every_s: float) -> None:
    """Record COUNT rectified pairs from RECIPE's camera into OUT, a folder the replay camera plays.

    OUT gets left/, right/ and calib.yaml; play it back with ``camera: {plugin: replay, settings: {path: OUT}}``.
    With ``--every``, one pair every so many seconds of the camera's own capture stamps.
    """
    from pydantic import ValidationError

    from core.contracts import PluginContext
    from core.registry import UnknownPlugin, default_registry
    from core.types import StereoFrame
    from core.unread_frames import UnreadFrames
    from drivers import sequence_folder as seq

    plugin_name, settings, recipe_dir = _camera_section(recipe, overrides)
    if (out / "left").is_dir() and any((out / "left").iterdir()):
        _fail(f"{out}: already holds a recorded sequence; choose a new folder")
    problem = make_folder(out)  # before the camera opens: a folder that cannot be made must not cost a recording
    if problem is not None:
        _fail(problem)
    try:
        plugin = default_registry().get("camera", plugin_name)
    except UnknownPlugin as exc:
        _fail(f"{recipe}: camera.plugin: {exc}")
    try:
        camera = plugin.spec.factory(dict(settings), PluginContext(recipe_dir=recipe_dir, recipe_name=recipe.stem))
    except (ValidationError, ValueError, TypeError, OSError) as exc:
        _fail(f"{recipe}: camera.settings: {' '.join(str(exc).split())[:300]}")

    written = errors = in_a_row = 0
    calib_written = False
    last_stamp = -math.inf
    unread = UnreadFrames(plugin.spec.answer("frame_rate", dict(settings), recipe_dir))
    not_recorded = 0
    try:
        for item in camera.frames():
            not_recorded += len(unread.between(item))  # captured while a pair was being written
            if not isinstance(item, StereoFrame):
                errors += 1
                in_a_row += 1
                click.echo(f"missed frame {item.index}: {item.message}", err=True)
                if in_a_row >= max_errors:
                    _fail(f"{in_a_row} frames missed in a row from the {plugin_name} camera; {written} of {count} recorded in {out}")
                continue
            in_a_row = 0
            if item.timestamp - last_stamp < every_s:
                continue  # read, so that the next pair recorded is the camera's newest, and let go
            last_stamp = item.timestamp
            if not calib_written:
                c = item.calib
                seq.write_calibration(out, {"focal_px": c.focal_px, "baseline_mm": c.baseline_mm, "cx": c.cx, "cy": c.cy,
                                            "width": c.width, "height": c.height, "doffs": c.doffs})
                calib_written = True
            seq.write_frame(out, f"{written:06d}", item.left, item.right)
            written += 1
            if every_s:  # hours between the first pair and the last: say each as it comes
                click.echo(f"{out}: pair {written} of {count} recorded"
                           + (f", the next in {every_s:g} s" if written < count else ""), err=True)
            if written >= count:
                break
    except KeyboardInterrupt:
        click.echo("interrupted", err=True)
    except OSError as exc:  # a full disk, a folder removed under it (the camera is closed below)
        _fail(f"{out}: cannot write pair {written} ({exc.strerror or exc}); {written} of {count} recorded")
    finally:
        camera.close()
    if not_recorded:
        click.echo(f"{out}: {not_recorded} frame(s) the camera captured were not recorded (writing a pair took longer "
                   f"than the camera's frame period, or its driver stalled): the sequence has gaps", err=True)
    if written < count:
        click.echo(f"{out}: {written} of {count} pairs recorded (the camera stopped), {errors} missed", err=True)
        raise click.exceptions.Exit(1 if written else 2)
    click.echo(f"{out}: {written} rectified pairs and calib.yaml recorded ({errors} missed frames)")


def _camera_section(recipe: Path, overrides: tuple[str, ...]) -> tuple[str, dict, Path]:
    """(plugin name, validated settings, recipe folder) of the recipe's camera section."""
    try:
        from core.recipe import RecipeError, load_recipe
    except ImportError:  # the recipe loader is not there: read the camera section alone
        return _camera_section_yaml(recipe)
    try:
        loaded = load_recipe(recipe, overrides)
    except RecipeError as exc:
        _fail(str(exc))
    return loaded.recipe.camera.plugin, loaded.plugin_settings.get("camera", loaded.recipe.camera.settings), loaded.directory


def _camera_section_yaml(recipe: Path) -> tuple[str, dict, Path]:
    import yaml

    from drivers.yaml_reader import Misread, safe_load

    try:
        data = safe_load(recipe.read_text())
    except OSError as exc:
        _fail(f"{recipe}: cannot read recipe ({exc.strerror})")
    except Misread as exc:
        _fail(f"{recipe}:{exc.line}: {exc.described}")
    except yaml.YAMLError as exc:
        _fail(f"{recipe}: YAML error: {str(exc).splitlines()[0]}")
    camera = (data or {}).get("camera") if isinstance(data, dict) else None
    if not isinstance(camera, dict) or not camera.get("plugin"):
        _fail(f"{recipe}: camera.plugin: required key missing")
    return camera["plugin"], dict(camera.get("settings") or {}), recipe.resolve().parent


def register(cli: click.Group) -> None:
    cli.add_command(plc_sim_command)
    camera = cli.commands.get("camera")
    if isinstance(camera, click.Group):
        camera.add_command(record_command)
