"""``inspect run``, ``validate``, ``plugins`` and ``report``."""
from __future__ import annotations

import math
import os
import signal
import sqlite3
import sys
from pathlib import Path

import click

from core.commands.params import cuda_if_present, out_file, overwritten_input
from core.recipe.schema import MAX_THREADS
from core.store import ROW_ID_MAX
from core.types import Alarm, OutputEvent, Status

# the progress line's words until the first part
WARMING_UP = "warming up (1-2 min the first time)"
_STYLE = {Status.PASS: "green", Status.REJECT: "bold red", Status.ERROR: "bold yellow", Status.FLAG: "bold magenta"}


def fail(message: str, code: int = 2) -> None:
    click.echo(f"error: {message}", err=True)
    sys.exit(code)


def distinct_folders(folders, what: str) -> None:
    """A one-line error (exit 2) where one of ``folders`` is not a folder (``what`` says what it should hold) or
    is given twice, under any name: its frames would count twice in every figure."""
    seen = {}
    for folder in folders:
        if not folder.is_dir():
            fail(f"{folder}: not {what}")
        if folder.resolve() in seen:
            fail(f"{folder}: given twice (also as {seen[folder.resolve()]})")
        seen[folder.resolve()] = folder


def replay_of(folder: Path, registry, ctx):
    """The ``replay`` camera over the sequence ``folder``; a one-line error naming the folder where it cannot
    be opened (its calibration, its images' layout)."""
    from pydantic import ValidationError

    from core.recipe.loader import first_problem
    from drivers.sequence_folder import SequenceError

    replay = registry.get("camera", "replay")
    try:
        return replay.spec.factory({"path": str(folder.resolve())}, ctx)
    except ValidationError as exc:
        fail(f"{folder}: {first_problem(exc, replay.spec.settings_model)[1]}")
    except (SequenceError, ValueError) as exc:  # the camera's own message may name the folder already
        fail(str(exc) if str(folder.resolve()) in str(exc) else f"{folder}: {exc}")


def _load(recipe: Path, overrides: tuple[str, ...], options: dict[str, str] | None = None):
    from core.recipe import RecipeError, load_recipe

    try:
        return load_recipe(recipe, overrides, options=options)
    except RecipeError as exc:
        fail(str(exc))


def _fmt(value: float | None, unit: str, signed: bool = False) -> str:
    if value is None:
        return "n/a"
    return f"{value:+.2f}{unit}" if signed else f"{value:.1f}{unit}"


def _with_sigma(value: float | None, sigma: float | None, unit: str, signed: bool = False) -> str:
    text = _fmt(value, unit, signed)
    if value is None or sigma is None:
        return text
    return text[: -len(unit)] + (f"±{sigma:.2f}" if signed else f"±{sigma:.1f}") + unit


def part_line(outcome) -> str:
    """One line per part: each defect's class, confidence, distance and deviation with their standard
    uncertainties (± u) and how it was measured where that is not as usual (along a groove), then what decided
    the verdict."""
    part = outcome.part
    defects = "; ".join(
        f"{m.detection.class_name} {m.detection.confidence:.2f} Z={_with_sigma(m.distance_mm, m.distance_sigma_mm, 'mm')}"
        f" dev={_with_sigma(m.deviation_mm, m.deviation_sigma_mm, 'mm', True)}"
        # a measurement's note; an unavailable one's is the verdict's reason already
        + (f" ({m.note})" if m.note and m.deviation_mm is not None else "")
        for m in part.measurements
    ) or "no defect"
    line = f"{part.part_id} frame {part.frame_id} {part.verdict.status.value:<6} {defects}"
    if part.verdict.reasons:  # a PASS can have reasons too: a rule it passed undecided (uncertain: pass)
        line += "  <- " + " | ".join(part.verdict.reasons)
    return line


@click.command("run")
@click.argument("recipe", type=click.Path(path_type=Path))
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE", help="override a recipe value (repeatable)")
@click.option("--device", default="auto", show_default=True, callback=cuda_if_present,
              help="torch device for plugins that use one")
@click.option("--max-frames", type=click.IntRange(min=1), default=None, help="stop after this many parts")
@click.option("--plc-sim", is_flag=True, help="start the Modbus PLC simulator in-process where a modbus output finds nothing listening")
@click.option("--quiet", is_flag=True, help="no per-part lines")
@click.option("--view", "view", is_flag=True, help="serve the operator web page (as the recipe's view.enabled)")
@click.option("--host", default=None, help="view: address to serve on (default: the recipe's view.host, 127.0.0.1)")
@click.option("--port", default=None, type=click.IntRange(1, 65535), help="view: port (default: the recipe's view.port, 8080)")
@click.option("--token", default=None, help="view: require this token from every browser (the recipe's view.token)")
@click.option("--keep-serving", is_flag=True, help="view: keep the page up after the run ends, until Ctrl-C")
@click.option("--threads", type=click.IntRange(1, MAX_THREADS), default=None,
              help="CPU threads for torch and OpenCV (the recipe's threads; default auto: half the cores)")
def run_command(recipe: Path, overrides: tuple[str, ...], device: str, max_frames: int | None, plc_sim: bool, quiet: bool,
                view: bool, host: str | None, port: int | None, token: str | None, keep_serving: bool,
                threads: int | None) -> None:
    """Inspect every part the recipe's camera delivers."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from core import engine

    loaded = _load(recipe, overrides + ((f"threads={threads}",) if threads else ()), {"threads": "--threads"})

    class LineConsole(Console):
        """The run's console, whose reader may go away (``inspect run | head``, a terminal's pipe closed). Rich
        raises SystemExit there, from inside the run loop, which then skipped finalising the run in the store
        and its alarms; here the output goes to /dev/null, ``gone`` says so, and the run stops as for SIGHUP."""

        gone = False

        def on_broken_pipe(self) -> None:
            self.quiet = self.gone = True
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())

    console = LineConsole(highlight=False, soft_wrap=True)
    if token is not None and len(token) < 8:
        fail("--token: use at least 8 characters")
    feed = server = None
    settings = loaded.recipe.view
    if keep_serving and not (view or settings.enabled):
        fail("--keep-serving: there is no page to keep up (add --view or set view.enabled)")
    # what inspect validate would say, once the options are known to be usable: the line runs as the recipe says
    for line in recipe_warnings(loaded):
        click.echo(line, err=True)
    if view or settings.enabled:
        from core.commands.view import start_view
        from core.view.feed import LiveFeed

        feed = LiveFeed()
        server = start_view(loaded.resolve(loaded.recipe.results.path), feed, host or settings.host, port or settings.port,
                            token or settings.token, settings.jpeg_quality, settings.max_fps,
                            echo=lambda line: console.print(line, style="bold cyan", markup=False))
    simulators = _start_plc_simulators(loaded, console) if plc_sim else []
    progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        TextColumn("{task.fields[fps]:.1f} fps"), console=console, transient=True)
    task = None

    def on_part(outcome) -> None:
        if feed is not None:
            feed.part(outcome)
        if not quiet:
            progress.console.print(part_line(outcome), style=_STYLE[outcome.part.verdict.status], markup=False)
        if task is not None:
            elapsed = progress.tasks[0].elapsed or 0.0
            done = progress.tasks[0].completed + 1
            progress.update(task, advance=1, fps=done / elapsed if elapsed else 0.0)

    def on_start(pipeline) -> None:
        if feed is not None:
            feed.started(loaded.recipe.name)
        total = getattr(pipeline.camera, "expected_frames", None)
        if max_frames is not None:
            total = min(total, max_frames) if total is not None else max_frames
        progress.update(task, description=loaded.recipe.name, total=total)

    def on_event(event: OutputEvent | Alarm) -> None:
        if isinstance(event, Alarm):
            progress.console.print(f"ALARM {event.source}: {event.message}", style="bold red", markup=False)
        elif event.output == "verify":  # the master parts' tally, before the first part
            progress.console.print(event.detail, style="cyan", markup=False)

    # systemctl stop sends SIGTERM, a closed terminal SIGHUP: both end the run as Ctrl-C does, after the
    # part in hand (its reject scheduled), delivering or alarming what is queued and finalising the run
    received: list[int] = []
    for signum in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, lambda number, _frame: received.append(number))
    try:
        with progress:
            # until the first part: a machine's first run compiles the kernels, a minute or two without a line
            task = progress.add_task(f"{loaded.recipe.name}: {WARMING_UP}", total=max_frames, fps=0.0)
            summary = engine.run(loaded, on_part=on_part, on_event=on_event, device=device, max_frames=max_frames,
                                 on_start=on_start, stop_requested=lambda: received[0] if received else
                                 (signal.SIGPIPE if console.gone else None))
    except engine.SetupError as exc:
        if server is not None:
            server.stop()
        fail(str(exc))
    finally:
        for sim in simulators:
            sim.stop()
        if feed is not None:
            feed.finished()
    c = summary.counts
    console.print(
        f"parts {sum(c.values())}  passed {c[Status.PASS]}  rejected {c[Status.REJECT]}  errors {c[Status.ERROR]}  "
        + (f"flagged {c[Status.FLAG]}  " if c[Status.FLAG] else "") +
        f"alarms {len(summary.alarms)}  {summary.fps:.2f} frames/s  ({summary.frames} frames in {summary.elapsed_s:.1f} s)",
        style="bold", markup=False,
    )
    if summary.frames and summary.stage_seconds:
        stages = ", ".join(f"{name} {1000 * seconds / summary.frames:.0f} ms" for name, seconds in summary.stage_seconds.items())
        console.print(f"mean per part: {stages}", markup=False)
    console.print(f"results: {loaded.resolve(loaded.recipe.results.path)}", markup=False)
    if server is not None:
        if keep_serving:
            from core.commands.view import serve_until_interrupted

            serve_until_interrupted(server, lambda: console.print(
                f"run finished; the page stays up at {server.url} until Ctrl-C", style="cyan", markup=False))
        else:
            server.stop()
    if summary.signal:
        console.print(f"stopped by {signal.Signals(summary.signal).name}: queued rejects were delivered or alarmed, "
                      "the run is finalised", style="yellow", markup=False)
    if summary.exit_code == engine.EXIT_ALARMS:
        for hint in alarm_hints(summary.alarms, loaded, plc_sim):
            console.print(hint, style="bold red", markup=False)
    elif summary.exit_code == engine.EXIT_PART_ERRORS:
        console.print("exit 3: some parts could not be inspected and were rejected as errors", style="yellow", markup=False)
    sys.exit(summary.exit_code)


def alarm_hints(alarms, loaded, plc_sim_given: bool) -> list[str]:
    """What exit 4 means for this run, one line per kind of alarm raised, from the alarms' causes."""
    causes = {a.cause for a in alarms}
    lines = [f"exit 4: {len(alarms)} alarm(s) were raised (above, and in the results store)"]
    if "link" in causes:
        outputs = {o.plugin for o in loaded.recipe.outputs}
        tcp = any(o.plugin == "modbus" and loaded.plugin_settings[f"outputs.{i}"].get("transport", "tcp") == "tcp"
                  for i, o in enumerate(loaded.recipe.outputs))
        where = "; ".join(sorted({a.message.split(" cannot be reached")[0] for a in alarms
                                  if a.cause == "link" and " cannot be reached" in a.message})) or "an output's peer"
        text = f"  {where} did not answer: check that it is on, wired and addressed as the recipe says"
        if tcp and not plc_sim_given:
            text += "; no PLC on this machine? run `inspect plc-sim` beside it or pass --plc-sim"
        elif "serial" in outputs:
            text += " (the serial port, its cable and the device at its other end)"
        lines.append(text)
    if "refused" in causes:
        lines.append("  the PLC answered but refused a command (the alarm says which and why): check the recipe's "
                     "addresses, unit and values against the PLC's program")
    if "late" in causes:
        lines.append("  parts were decided after their reject was due: the inspection takes longer than the time from "
                     "the camera to the actuator; lengthen the delay, or speed it up (stereo.region: defects, "
                     "stereo.scale, threads; docs/benchmarks.md)")
    if causes & {"release", "pulse"}:
        lines.append("  reject pulses were cut or would have merged: parts come closer together than the pulse allows; "
                     "shorten pulse_ms or count parts in a register (write: counter)")
    if "crash" in causes:
        lines.append("  an earlier run ended without finishing: check those parts by hand (`inspect report` lists them)")
    if any(a.source == "camera" and a.cause not in ("frozen", "image", "behind") for a in alarms):
        lines.append("  the camera stopped delivering frames")
    if "behind" in causes:
        lines.append("  frames the camera captured were not read, and their plates went by unseen (rejected as "
                     "ERROR): the inspection is slower than the camera (lower its frame rate to the plates' rate, or "
                     "speed the inspection up: `inspect bench`, stereo.region: defects, stereo.scale, threads), or "
                     "its driver stalled")
    if "frozen" in causes:
        lines.append("  the camera delivered the same images again (a stalled driver or USB stream): check its "
                     "cable and driver; the parts it did not see were rejected")
    if "image" in causes:
        lines.append("  the camera's images could not show a defect (too dark, washed out, without texture, or one "
                     "eye's image as both): check the lights, the exposure, both lenses and the camera's driver "
                     "(camera.image_check, docs/recipe-reference.md)")
    if "range" in causes:
        lines.append("  the plates lie outside the stereo search range (the alarm says at what distance): set "
                     "stereo.working_distance_mm to where they are, or the camera back where the recipe expects it")
    if "swapped" in causes:
        lines.append("  the camera delivers its right eye's image as the left, or hangs upside down: exchange the eyes "
                     "in the camera's settings or wiring (its left eye is the one on the left seen from behind it), "
                     "or turn it")
    if "unmatched" in causes:
        lines.append("  the camera's left and right images show no common scene: check that both eyes are exposed "
                     "together and that their images reach the computer whole (the camera's cable, its driver)")
    if "rectification" in causes:
        lines.append("  the camera's images are not rectified as its calibration file says (their rows lie apart by "
                     "the amount the alarm gives): check that camera.settings.calibration is this camera's file (its "
                     "serial number), or have the camera recalibrated if it was knocked or opened")
    if "store" in causes:
        lines.append("  the results store could not be written (a full disk, its permissions, a removed drive): the "
                     "parts decided until then went to the outputs unrecorded; free the disk and start again")
    if "images" in causes:
        lines.append("  the parts' annotated images could no longer be saved (the results disk nearly full, the images "
                     "folder not writable): every decision was still stored and sent; free the disk")
    if "verify" in causes:
        lines.append(f"  no plate was inspected: the master parts (verify.path) did not come out as their labels say; "
                     f"`inspect eval depth {loaded.resolve(loaded.recipe.verify.path)} --recipe {loaded.path} --boxes "
                     f"detector` (with this run's --set options) shows, defect by defect, what the detector missed "
                     f"and what depth measured")
    if "stall" in causes:
        lines.append(f"  a stage, plugin or camera stopped returning for longer than watchdog_s "
                     f"({loaded.recipe.watchdog_s:g} s; the alarm names the frame or the camera): the outputs told the "
                     "line the inspection was not ready meanwhile")
    return lines


def _start_plc_simulators(loaded, console) -> list:
    """Start the in-process PLC simulator for each Modbus TCP output whose port has no listener."""
    started = []
    for index, output in enumerate(loaded.recipe.outputs):
        if output.plugin != "modbus":
            continue
        settings = loaded.plugin_settings[f"outputs.{index}"]
        host, port = settings.get("host"), settings.get("port")
        if not host or not port or settings.get("transport", "tcp") != "tcp":
            continue
        from drivers import plc_sim

        if plc_sim.is_listening(host, port):
            console.print(f"PLC at {host}:{port} answers; not starting the simulator", markup=False)
            continue
        console.print(f"nothing listens on {host}:{port}: starting the PLC simulator in-process there", style="cyan", markup=False)
        started.append(plc_sim.serve_in_thread(host, port, on_change=lambda line: console.print(f"  PLC {line}", style="cyan", markup=False)))
    return started


@click.command("validate")
@click.argument("recipe", type=click.Path(path_type=Path))
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE")
def validate_command(recipe: Path, overrides: tuple[str, ...]) -> None:
    """Check a recipe (keys, types, ranges, plugins, files) without running it."""
    loaded = _load(recipe, overrides)
    r = loaded.recipe
    from core.store import store_problem

    results = store_problem(loaded.resolve(r.results.path))
    if results is not None:
        fail(loaded.describe(("results", "path"), results))
    memory = _stereo_memory_problem(loaded)
    if memory is not None and r.stereo.region == "full":
        fail(loaded.describe(("stereo",), memory))
    click.echo(
        f"{recipe}: ok (recipe {r.name!r}, camera {r.camera.plugin}, stereo {r.stereo.backend}, detector {r.detector.plugin}, "
        f"{len(r.decision.rules)} rules, outputs {', '.join(o.plugin for o in r.outputs) or 'none'}"
        f"{_master_parts_said(loaded)})"
    )
    for line in recipe_warnings(loaded):
        click.echo(line, err=True)
    if memory is not None:
        click.echo(loaded.describe(("stereo",), f"warning: a box covering most of the frame would be its part's "
                                                 f"ERROR: {memory}"), err=True)


def _stereo_memory_problem(loaded) -> str | None:
    """``core.stereo_memory.recipe_problem`` with the recipe's stereo backend built from its settings, as
    ``inspect run`` builds it; None where the backend cannot be built (inspect run reports that)."""
    from core.contracts import PluginContext
    from core.registry import default_registry
    from core.stereo_memory import recipe_problem

    registry = default_registry()
    try:
        backend = registry.get("stereo", loaded.recipe.stereo.backend).spec.factory(
            loaded.plugin_settings["stereo"], PluginContext(recipe_dir=loaded.directory))
    except Exception:
        return None
    return recipe_problem(loaded, backend, registry)


def recipe_warnings(loaded) -> list[str]:
    """What the recipe lets through without an error: limits the camera cannot resolve at the working
    distance, classes no rule covers, decisions that pass unproven parts, image checks turned off, rejects
    that reach no actuator or come faster than it can be pulsed, more threads than the machine has cores,
    deviation rules written the wrong way round, master parts none of which is defective, and what each plugin
    says of its own settings."""
    return (_depth_warnings(loaded) + _detector_warnings(loaded) + _coverage_warnings(loaded)
            + _guard_band_warnings(loaded) + _image_check_warnings(loaded) + _output_warnings(loaded)
            + _output_timing_warnings(loaded) + _thread_warnings(loaded) + _rule_warnings(loaded)
            + _verify_warnings(loaded) + _plugin_warnings(loaded))


def _master_verdicts(loaded):
    """What the labels of each master part (``verify.path``) call for under the recipe's rules, by frame
    (``core.verification.known_verdicts``); None where the recipe names no master parts."""
    from core.verification import known_verdicts

    if loaded.recipe.verify.path is None:
        return None
    return known_verdicts(loaded.resolve(loaded.recipe.verify.path), loaded.recipe.decision)


def _master_parts_said(loaded) -> str:
    """What ``verify.path`` holds, for ``validate``'s line: ``, master parts N (D defective)``, or that there are
    none."""
    known = _master_verdicts(loaded)
    if known is None:
        return ", no master parts"
    return f", master parts {len(known)} ({sum(status is Status.REJECT for status in known.values())} defective)"


def _verify_warnings(loaded) -> list[str]:
    """A line where the recipe names no master parts (``verify.path``), or where they hold no part that the
    recipe's limits clearly reject: such parts pass the check whatever the detector finds, and vouch for
    nothing."""
    known = _master_verdicts(loaded)
    if known is None:
        return [loaded.describe(("verify", "path"), "warning: no master parts: a detector that finds nothing (weights "
                                                   "that score low, a confidence set too high) passes every part "
                                                   "unnoticed; name a recording of known parts (docs/recipe-reference.md, "
                                                   "verify)")]
    if any(status is Status.REJECT for status in known.values()):
        return []
    return [loaded.describe(("verify", "path"), f"warning: none of the {len(known)} parts in "
                                               f"{loaded.resolve(loaded.recipe.verify.path)} has a defect clearly "
                                               f"beyond a limit of this recipe's rules: the check passes whatever the "
                                               f"detector finds (add a rejected master part)")]


def _plugin_warnings(loaded) -> list[str]:
    """Each plugin's own warnings about its settings (``PluginSpec.warnings``), under the recipe key of each."""
    from core.recipe.loader import detector_settings
    from core.registry import default_registry

    registry, recipe = default_registry(), loaded.recipe
    plugins = [("camera", recipe.camera.plugin, ("camera",), loaded.plugin_settings["camera"]),
               ("stereo", recipe.stereo.backend, ("stereo",), loaded.plugin_settings["stereo"]),
               ("detector", recipe.detector.plugin, ("detector",), detector_settings(loaded))]
    plugins += [("output", o.plugin, ("outputs", i), loaded.plugin_settings[f"outputs.{i}"])
                for i, o in enumerate(recipe.outputs)]
    lines = []
    for kind, name, section, settings in plugins:
        for key, text in registry.get(kind, name).spec.answer("warnings", settings, loaded.directory) or []:
            lines.append(loaded.describe((*section, "settings", key), f"warning: {text}"))
    return lines


def _rule_warnings(loaded) -> list[str]:
    """A line for each deviation rule written the wrong way round (``core.decision.holds_at_the_surface``)."""
    from core.decision import holds_at_the_surface

    flipped = {">": "<", ">=": "<=", "<": ">", "<=": ">="}
    lines = []
    for index, rule in enumerate(loaded.recipe.decision.rules):
        if holds_at_the_surface(rule):
            beyond = "deeper" if rule.op in ("<", "<=") else "higher"
            lines.append(loaded.describe(
                ("decision", "rules", index),
                f"warning: deviation_mm {rule.op} {rule.threshold:g} holds for a defect level with the surface: it "
                f"rejects those and passes every defect {beyond} than {abs(rule.threshold):g} mm (did you mean "
                f"{flipped[rule.op]} {rule.threshold:g}?)"))
    return lines


def _thread_warnings(loaded) -> list[str]:
    """A line where ``threads`` asks each stage for more threads than this machine has cores: they spin against
    each other and against the stage running beside them (docs/recipe-reference.md)."""
    threads, cores = loaded.recipe.threads, os.cpu_count()
    if threads == "auto" or not cores or int(threads) <= cores:
        return []
    return [loaded.describe(("threads",), f"warning: {threads} threads per stage on this machine's {cores} cores: "
                                          f"the threads beyond the cores spin against each other and slow the "
                                          f"line (auto: half the cores)")]


def _detector_warnings(loaded) -> list[str]:
    """Lines for detector settings that drop defects before any rule sees them: a confidence no score
    reaches, classes the detector reports that ``detector.classes`` leaves out."""
    detector = loaded.recipe.detector
    lines = []
    if detector.confidence >= 1.0:
        lines.append(loaded.describe(("detector", "confidence"), f"warning: {detector.confidence:g} keeps only "
                                     f"detections scored {detector.confidence:g} or more, which a detector's scores "
                                     f"do not reach: nothing is detected and every part passes"))
    known = loaded.detector_classes
    if known is not None and detector.classes is not None:
        left_out = [c for c in known if c not in detector.classes]
        if left_out:
            lines.append(loaded.describe(("detector", "classes"), f"warning: leaves out {', '.join(left_out)}, which "
                                         f"the detector reports: such a defect is not kept, and its part passes "
                                         f"(null keeps every class)"))
    return lines


def _output_timing_warnings(loaded) -> list[str]:
    """Lines for outputs whose timing the camera's frame rate defeats: an actuator that cannot be given two parts
    as close together as the camera delivers them (``PluginSpec.part_interval``), where a run of rejects falls
    behind, one pulse after another, until the output alarms them instead of sending them; and one that still
    sends a command, counted delivered, as late as the camera's next plate (``PluginSpec.late_limit``), where
    such a reject can reach the next plate instead of its own and the defective one passes."""
    from core.recipe.loader import camera_answer, output_answers
    from core.registry import default_registry

    registry = default_registry()
    fps = camera_answer(loaded, registry, "frame_rate")
    if not fps:
        return []
    period = 1.0 / fps
    pulses = [loaded.describe(
        ("outputs", index, "settings"),
        f"warning: a part's pulse and the low after it take {1000 * interval:.0f} ms, longer than the "
        f"{1000 * period:.0f} ms between two plates at {fps:g} per second: each reject right after another "
        f"is {1000 * (interval - period):.0f} ms later than the one before, until beyond max_late_ms it is "
        f"alarmed instead of sent (a shorter pulse_ms, or write: counter)")
        for index, interval in output_answers(loaded, registry, "part_interval") if interval > period]
    late = [loaded.describe(
        ("outputs", index, "settings", "max_late_ms"),
        f"warning: a command up to {1000 * limit:.0f} ms late is still sent, but plates come "
        f"{1000 * period:.0f} ms apart at {fps:g} per second: a reject that late can reach the next "
        f"plate instead of its own, counted delivered (give max_late_ms less than {1000 * period:.0f})")
        for index, limit in output_answers(loaded, registry, "late_limit") if limit >= period]
    return pulses + late


def _image_check_warnings(loaded) -> list[str]:
    """A line for each of ``camera.image_check``'s tests that the recipe turns off: a frame that shows no
    plate is then decided on its (absent) detections, and its part passes."""
    check = loaded.recipe.camera.image_check
    off = [(key, what) for key, value, limit, what in (
        ("min_mean_grey", check.min_mean_grey, 0.0, "a dark image (the lights off, a covered lens)"),
        ("max_saturated", check.max_saturated, 1.0, "a blinded image"),
        ("min_texture", check.min_texture, 0.0, "an image without detail (out of focus, fogged)"),
    ) if value == limit]
    return [loaded.describe(("camera", "image_check", key), f"warning: off: {what} finds no defect, and its part "
                            f"passes instead of being an ERROR") for key, what in off]


def _output_warnings(loaded) -> list[str]:
    if loaded.recipe.outputs:
        return []
    return [loaded.describe(("outputs",), "warning: no output: a rejected part is stored but reaches no actuator "
                                          "(add a modbus or serial output, or log to see the commands)")]


def _coverage_warnings(loaded) -> list[str]:
    """A line naming the classes the detector reports (those ``detector.classes`` keeps) that no rule covers:
    a defect of theirs passes whatever its depth."""
    from core.decision import unruled_classes

    recipe = loaded.recipe
    known = loaded.detector_classes
    if known is None:
        return []
    kept = [c for c in known if recipe.detector.classes is None or c in recipe.detector.classes]
    unruled = unruled_classes(recipe.decision, kept)
    if not unruled:
        return []
    which = "every class the detector reports" if len(unruled) == len(kept) else ", ".join(unruled)
    return [loaded.describe(("decision",), f"warning: no rule covers {which}: such a defect passes whatever is "
                                           f"measured (add a rule for it or for class any, or set "
                                           f"reject_unruled_defects: true)")]


def _guard_band_warnings(loaded) -> list[str]:
    """Lines for decision settings that let a part pass whose conformance was not proven (ISO 14253-1): an
    undecided measurement passed (``uncertain: pass``), or a guard band narrower than the measurement's
    standard uncertainty (``coverage_factor`` below 1)."""
    decision = loaded.recipe.decision
    lines = []
    if decision.uncertain == "pass" and decision.rules:
        lines.append(loaded.describe(("decision", "uncertain"), "warning: uncertain: pass lets a part pass whose "
                                     "measurement lies within the guard band of a limit, so it may be out of "
                                     "tolerance (with reject or flag only parts proven inside every limit pass)"))
    if decision.coverage_factor < 1.0 and decision.rules:
        k = decision.coverage_factor
        beyond = 0.5 * math.erfc(k / math.sqrt(2.0))  # a normal error's chance to exceed k standard deviations
        lines.append(loaded.describe(("decision", "coverage_factor"), f"warning: a guard band of {k:g} u passes a "
                                     f"part measured {k:g} u inside a limit, whose true value lies beyond it with "
                                     f"a probability of {beyond:.0%} (with 2 u, the default, 2 %)"))
    return lines


def _depth_warnings(loaded) -> list[str]:
    """Rules the camera cannot resolve at the working distance (``core.resolution``), from the geometry
    the camera plugin states without opening the device; a line saying so where it states none."""
    from core.contracts import PluginContext
    from core.registry import default_registry
    from core.resolution import resolution_warnings

    spec = default_registry().get("camera", loaded.recipe.camera.plugin).spec
    if spec.calibration is None:
        return [f"{loaded.where(('camera',))}: camera: note: plugin {loaded.recipe.camera.plugin} gives no geometry "
                "before it runs, so whether the rules' limits can be resolved was not checked"]
    try:
        calib = spec.calibration(loaded.plugin_settings["camera"], PluginContext(recipe_dir=loaded.directory))
    except Exception as exc:  # the camera's own reason, e.g. no calibration file
        return [f"{loaded.where(('camera',))}: camera: note: resolution not checked: {exc}"]
    return resolution_warnings(loaded, calib)


@click.command("plugins")
def plugins_command() -> None:
    """List every camera, stereo backend, detector and output plugin found, with its package."""
    from core.registry import default_registry

    registry = default_registry()
    for kind in ("camera", "stereo", "detector", "output"):
        click.echo(f"{kind}:")
        for name in registry.names(kind):
            plugin = registry.get(kind, name)
            click.echo(f"  {name:<14} {plugin.package:<28} {plugin.spec.description}")
    for line in registry.conflicts():
        click.echo(f"conflict: {line}", err=True)
    for line in registry.failed:
        click.echo(f"failed to load: {line}", err=True)


WITHOUT_ACCOUNT = "no account of it (the matcher's map alone)"


@click.command("report")
@click.argument("results", type=click.Path(path_type=Path))
@click.option("--run", "run_id", type=int, default=None, help="one run only (default: all runs in the store)")
@click.option("--csv", "csv_path", type=click.Path(path_type=Path), default=None, callback=out_file,
              help="export one row per defect")
def report_command(results: Path, run_id: int | None, csv_path: Path | None) -> None:
    """Yield and counts per class from a results store (folder or results.db)."""
    from core import store

    db_file = store.db_path(results)
    # the store and SQLite's journal beside it: a CSV written over either is the inspection record lost
    overwrite = overwritten_input({"--csv": csv_path}, [db_file, db_file.with_name(db_file.name + "-wal")])
    if overwrite is not None:
        fail(overwrite)
    try:
        db = store.open_readonly(results)
    except (FileNotFoundError, store.StoreError) as exc:
        fail(str(exc))
    try:
        _report(db, results, run_id, csv_path)
    except sqlite3.DatabaseError as exc:  # the schema read, a page further in did not
        fail(str(store.damaged(db_file, exc)))


def _report(db, results: Path, run_id: int | None, csv_path: Path | None) -> None:
    """``report_command``'s lines from the open store ``db``."""
    from core import store

    runs = db.execute("SELECT COUNT(*) FROM runs").fetchone()[0]
    if run_id is not None and (abs(run_id) > ROW_ID_MAX  # beyond SQLite's integers: no run, and no query to ask
                               or db.execute("SELECT 1 FROM runs WHERE id = ?", (run_id,)).fetchone() is None):
        # a mistyped run would otherwise read as a run without parts
        first, last = db.execute("SELECT MIN(id), MAX(id) FROM runs").fetchone()
        fail(f"{store.db_path(results)}: no run {run_id} (" + (f"runs {first}-{last})" if runs else "no runs yet)"))
    s = store.summary(db, run_id)
    click.echo(f"{store.db_path(results)}: {runs} run(s){'' if run_id is None else f', run {run_id}'}")
    yield_text = "n/a" if s["yield_percent"] is None else f"{s['yield_percent']:.1f}%"
    for row in store.crashed_runs(db, run_id):
        click.echo(f"run {row['id']} crashed (never finished): {row['parts']} parts, {row['unconfirmed']} of them "
                   "rejected without a confirmed output: check them by hand", err=False)
    for run, started, text in store.master_part_checks(db, run_id):
        click.echo(f"run {run} " + (f"checked its {text}" if started else f"did not start: {text}"))
    flagged = f"  flagged {s['flagged']}" if s["flagged"] else ""
    click.echo(f"parts {s['parts']}  passed {s['passed']}  rejected {s['rejected']}  errors {s['errors']}{flagged}  "
               f"yield {yield_text}  alarms {s['alarms']}")
    if s["defects_per_class"]:
        click.echo("defects per class (by defect verdict):")
        for cls, by_verdict in s["defects_per_class"].items():
            detail = ", ".join(f"{v} {n}" for v, n in sorted(by_verdict.items()))
            click.echo(f"  {cls:<16} {sum(by_verdict.values()):>4}  ({detail})")
    undecided = store.undecided_by_cause(db, run_id)
    if undecided:
        from core.uncertainty_budget import kind_name

        click.echo("defects no rule could decide, by the largest part of their uncertainty:")
        for kind, n in undecided.items():
            click.echo(f"  {n:>4}  {kind_name(kind) if kind else WITHOUT_ACCOUNT}")
    if csv_path is not None:
        n = store.export_csv(db, csv_path, run_id)  # a file it cannot write: OSError naming it, for cli.main
        click.echo(f"wrote {n} rows to {csv_path}")


def register(cli: click.Group) -> None:
    for command in (run_command, validate_command, plugins_command, report_command):
        cli.add_command(command)
