"""``inspect bench``: every stage timed on the same frames, per stereo backend."""
from __future__ import annotations

import json
from pathlib import Path

import click
from pydantic import ValidationError

from core.commands.inspection import _load, fail
from core.commands.params import FINITE, cuda_if_present, demo_recipe, out_folder
from core.recipe.schema import MAX_THREADS
from drivers.file_writes import write_text
from drivers.yaml_reader import Misread, option_value
from drivers.zed_calibration import RESOLUTIONS as ZED_MODES


@click.command("bench")
@click.option("--recipe", "recipe", default=demo_recipe(), type=click.Path(path_type=Path),
              show_default=True, help="camera (the frames), detector, depth and decision come from here")
@click.option("--sequence", type=click.Path(path_type=Path), default=None,
              help="another recorded sequence folder (scaled to --resolution unless it is that size)")
@click.option("--backends", default="opencv_sgbm,torch_sgm", show_default=True, help="comma-separated stereo backends")
@click.option("--resolution", type=click.Choice([name.lower() for name in ZED_MODES]), default="wvga", show_default=True,
              help="the frames scaled to this ZED mode, their calibration with them")
@click.option("--min-disp", type=FINITE, default=None)
@click.option("--max-disp", type=FINITE, default=None)
@click.option("--device", default="cpu", show_default=True, callback=cuda_if_present, help="cpu, cuda or auto")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(1, 100))
@click.option("--frames", default=None, type=click.IntRange(1), help="use only the first N frames")
@click.option("--regions", default="full,defects", show_default=True,
              help="comma-separated: full (stereo on every whole frame) and/or defects (stereo.region: defects, "
                   "compared with full-frame depth)")
@click.option("--out", default=Path("results/bench"), type=click.Path(path_type=Path), show_default=True,
              callback=out_folder)
@click.option("--soak", default=None, type=click.IntRange(1), metavar="FRAMES",
              help="instead of the table: run the real loop (the recipe's backend and region) for FRAMES frames of a "
                   "looped replay and report resident memory at the start and end")
@click.option("--soak-every", default=1000, show_default=True, type=click.IntRange(1), help="soak: sample RSS every N frames")
@click.option("--quiet", is_flag=True, help="soak: no line per sample")
@click.option("--live", default=None, type=click.IntRange(1), metavar="FRAMES",
              help="after the table: the real loop as the recipe runs it (detection a frame ahead where "
                   "stereo.concurrent) for FRAMES frames, with detection alone, with the matcher's depth "
                   "(depth.method: disparity) and with the recipe's depth, in --live-rounds rounds, and their ratio")
@click.option("--live-rounds", default=3, show_default=True, type=click.IntRange(1),
              help="live: rounds of every loop, their order reversed each round; the ratio is the rounds' median")
@click.option("--threads", type=click.IntRange(1, MAX_THREADS), default=None,
              help="torch and OpenCV CPU threads (1 is fastest when another job keeps a core busy)")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE")
@click.option("--versus", "versus", multiple=True, metavar="KEY=VALUE",
              help="compare every defect's depth with the recipe's stereo backend run full-frame with this setting "
                   "changed (e.g. --versus search=full); repeatable")
def bench_command(recipe, sequence, backends, resolution, min_disp, max_disp, device, repeats, frames, regions, out,
                  soak, soak_every, quiet, live, live_rounds, threads, overrides, versus):
    """Time capture, detection, stereo, depth, decision, outputs and the whole loop; print and save
    a table (JSON + Markdown). Backend "none" times detection alone."""
    from core.bench import (NO_STEREO, BenchInputError, add_own_share, live_markdown, markdown, run_bench, run_live,
                            run_soak)
    from core.engine import SetupError, command_threads
    from core.registry import default_registry

    overrides = list(overrides)
    if sequence is not None:
        overrides.append(f"camera.settings.path={sequence.resolve()}")
    if (min_disp is None) != (max_disp is None):
        fail("give both --min-disp and --max-disp")
    if live is None and click.get_current_context().get_parameter_source("live_rounds") \
            is click.core.ParameterSource.COMMANDLINE:
        fail("--live-rounds needs --live FRAMES")
    if max_disp is not None:
        overrides += ["stereo.working_distance_mm=null", f"stereo.min_disparity={min_disp}", f"stereo.max_disparity={max_disp}"]
    if threads:
        overrides.append(f"threads={threads}")  # so that the soak's real loop keeps them too
    loaded = _load(recipe, tuple(overrides), {"camera.settings.path": "--sequence",
                                              "stereo.min_disparity": "--min-disp", "stereo.max_disparity": "--max-disp",
                                              "threads": "--threads"})
    registry = default_registry()
    command_threads(threads)
    if soak is not None:
        try:
            report = run_soak(loaded, registry, soak, device, soak_every,
                              None if quiet else lambda n, mb: click.echo(f"frame {n}: RSS {mb:.0f} MB"))
        except SetupError as exc:
            fail(str(exc))
        out.mkdir(parents=True, exist_ok=True)
        write_text(out / "soak.json", json.dumps(report, indent=2))
        click.echo(f"soak: {report['frames']} frames in {report['seconds']:.0f} s ({report['fps']:.2f} fps); RSS "
                   f"{report['rss_start_mb']:.0f} MB after the first frame, {report['rss_end_mb']:.0f} MB at the end, "
                   f"peak {report['peak_rss_mb']:.0f} MB; saved: {out / 'soak.json'}")
        return
    names = [b.strip() for b in backends.split(",") if b.strip()]
    known = registry.names("stereo")
    unknown = [b for b in names if b not in known and b != NO_STEREO]
    if not names:
        fail(f"--backends: give at least one of {', '.join(known)}, or {NO_STEREO}")
    if unknown:
        fail(f"--backends: unknown stereo backend {', '.join(unknown)}; known: {', '.join(known)}, or {NO_STEREO}")
    region_names = tuple(r.strip() for r in regions.split(",") if r.strip())
    if not region_names or any(r not in ("full", "defects") for r in region_names):
        fail(f"--regions: give full and/or defects, not {regions!r}")
    reference = {}
    for item in versus:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            fail(f"--versus: expected KEY=VALUE, got {item!r}")
        try:
            reference[key.strip()] = option_value(value)
        except Misread as exc:
            fail(f"--versus {item}: {exc.described}")
    if reference and loaded.recipe.stereo.backend not in names:
        fail(f"--versus changes the recipe's stereo backend {loaded.recipe.stereo.backend}, which --backends leaves out")
    if reference:
        try:
            spec = registry.get("stereo", loaded.recipe.stereo.backend).spec
            if spec.settings_model is not None:
                spec.settings_model(**{**loaded.plugin_settings["stereo"], **reference})
        except ValidationError as exc:
            fail(f"--versus: {exc.errors()[0]['loc'][0]}: {exc.errors()[0]['msg']}")
    try:
        report = run_bench(loaded, registry, names, resolution, device, repeats, frames, region_names, reference or None)
    except BenchInputError as exc:
        fail(f"{loaded.recipe.camera.settings.get('path', 'the camera')}: {exc}")
    except SetupError as exc:
        fail(str(exc))
    table = markdown(report)
    if live is not None:
        report["live"] = run_live(loaded, registry, live, device, live_rounds)
        add_own_share(report["live"], report, loaded.recipe.stereo.backend, loaded.recipe.stereo.region)
        table += "\n" + live_markdown(report["live"])
    out.mkdir(parents=True, exist_ok=True)
    stem = f"bench-{resolution}-{report['device']}"
    write_text(out / f"{stem}.json", json.dumps(report, indent=2))
    write_text(out / f"{stem}.md", table)
    click.echo(table)
    click.echo(f"saved: {out / (stem + '.json')}, {out / (stem + '.md')}")


def register(cli: click.Group) -> None:
    cli.add_command(bench_command)
