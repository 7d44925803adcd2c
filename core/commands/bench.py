"""``inspect bench``: every stage timed on the same frames, per stereo backend."""
from __future__ import annotations

import json
from pathlib import Path

import click

from core.commands.inspection import _load, fail


@click.command("bench")
@click.option("--recipe", "recipe", default=Path("recipes/steel_plate.yaml"), type=click.Path(path_type=Path),
              show_default=True, help="camera (the frames), detector, depth and decision come from here")
@click.option("--sequence", type=click.Path(path_type=Path), default=None, help="another recorded sequence folder")
@click.option("--backends", default="opencv_sgbm,torch_sgm", show_default=True, help="comma-separated stereo backends")
@click.option("--resolution", type=click.Choice(["wvga", "hd720"]), default="wvga", show_default=True)
@click.option("--min-disp", type=float, default=None)
@click.option("--max-disp", type=float, default=None)
@click.option("--device", default="cpu", show_default=True, help="cpu, cuda or auto")
@click.option("--repeats", default=3, show_default=True, type=click.IntRange(1, 100))
@click.option("--frames", default=None, type=click.IntRange(1), help="use only the first N frames")
@click.option("--out", default=Path("results/bench"), type=click.Path(path_type=Path), show_default=True)
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE")
def bench_command(recipe, sequence, backends, resolution, min_disp, max_disp, device, repeats, frames, out, overrides):
    """Time capture, detection, stereo, depth, decision, outputs and the whole loop; print and save
    a table (JSON + Markdown)."""
    from core.bench import markdown, run_bench
    from core.registry import default_registry

    overrides = list(overrides)
    if sequence is not None:
        overrides.append(f"camera.settings.path={sequence.resolve()}")
    if (min_disp is None) != (max_disp is None):
        fail("give both --min-disp and --max-disp")
    if max_disp is not None:
        overrides += ["stereo.working_distance_mm=null", f"stereo.min_disparity={min_disp}", f"stereo.max_disparity={max_disp}"]
    loaded = _load(recipe, tuple(overrides))
    registry = default_registry()
    names = [b.strip() for b in backends.split(",") if b.strip()]
    known = registry.names("stereo")
    unknown = [b for b in names if b not in known]
    if unknown:
        fail(f"--backends: unknown stereo backend {', '.join(unknown)}; known: {', '.join(known)}")
    report = run_bench(loaded, registry, names, resolution, device, repeats, frames)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"bench-{resolution}-{report['device']}"
    (out / f"{stem}.json").write_text(json.dumps(report, indent=2))
    table = markdown(report)
    (out / f"{stem}.md").write_text(table)
    click.echo(table)
    click.echo(f"saved: {out / (stem + '.json')}, {out / (stem + '.md')}")


def register(cli: click.Group) -> None:
    cli.add_command(bench_command)
