"""``inspect eval depth-suite``: every evaluation set rendered where missing, every group scored, one row each."""
from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import click

from core.commands.params import out_folder
from core.depth_suite import SUITE
from core.recipe.schema import MAX_THREADS
from core.report_text import number, percent
from drivers.file_writes import write_text

RUN_INSPECT = (sys.executable, "-c", "from core.cli import main; main()")  # the same Python, as a user types it


def _inspect(args: list[str]) -> tuple[int, str]:
    """Run ``inspect ARGS`` in a process of its own: (exit status, its error output's last line)."""
    done = subprocess.run([*RUN_INSPECT, *args], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines = [line for line in done.stderr.splitlines() if line.strip()]
    return done.returncode, (lines[-1] if lines else f"exit status {done.returncode}")


def _without_prefix(line: str) -> str:
    return line[len("error: "):] if line.lower().startswith("error: ") else line


@click.command("depth-suite")
@click.argument("root", default=Path("runs"), type=click.Path(file_okay=False, path_type=Path))
@click.option("--suite", "suite_path", default=SUITE, show_default="sim/eval_sets.yaml",
              type=click.Path(dir_okay=False, path_type=Path), help="the sets and groups")
@click.option("--group", "groups", multiple=True, metavar="NAME", help="score only this group (repeatable)")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE",
              help="override a recipe value in every group, e.g. depth.method=disparity (repeatable)")
@click.option("--out", type=click.Path(path_type=Path), default=Path("runs/depth_suite"), show_default=True,
              callback=out_folder)
@click.option("--against", type=click.Path(exists=True, file_okay=False, path_type=Path), default=None,
              help="an earlier --out: the defects each group now decides differently")
@click.option("--threads", type=click.IntRange(1, MAX_THREADS), default=None, help="torch and OpenCV CPU threads")
def eval_depth_suite_command(root, suite_path, groups, overrides, out, against, threads):
    """Render the evaluation sets of the suite that ROOT (runs/) lacks, run `inspect eval depth` on each of
    its groups (their reports in OUT/GROUP/) and print one row per group: the deviation's error against the
    floor, the uncertainty's calibration, the distance, and the decisions at the recipe's rules. Saves
    OUT/suite.md and OUT/suite.json. With --against an earlier OUT, says per group which defects are now
    proven or no longer proven on their side of a limit, and how many each run proved on the wrong side, however
    near the limit, and of those clear-cut and beyond it."""
    from core import depth_suite as ds
    from core.commands.inspection import fail

    try:
        suite = ds.load_suite(suite_path)
        chosen = suite.chosen(groups)
    except ds.SuiteError as exc:
        fail(str(exc))
    for name in dict.fromkeys(s for g in chosen for s in g.sets):
        if ds.is_rendered(root / name):
            continue
        args = suite.render_args(name, root)
        click.echo(f"rendering {name}: inspect {' '.join(args)}")
        start = time.perf_counter()
        code, said = _inspect(args)
        if code != 0:
            fail(f"set {name} ({suite.path}): {_without_prefix(said)}")
        click.echo(f"  {time.perf_counter() - start:.0f} s")
    extra = [word for o in overrides for word in ("--set", o)] + ([] if threads is None else ["--threads", str(threads)])
    rows, changes, commands, machine = [], {}, {}, ""
    began = time.perf_counter()
    for group in chosen:
        args = ["eval", "depth", *[str(root / s) for s in group.sets], *group.options, *extra,
                "--out", str(out / group.name), "--quiet", "--no-figure"]
        commands[group.name] = "inspect " + " ".join(args)
        start = time.perf_counter()
        code, said = _inspect(args)
        if code != 0:
            fail(f"group {group.name} ({suite.path}): {_without_prefix(said)}")
        body = json.loads((out / group.name / "depth_eval.json").read_text())
        machine = machine or body.get("machine", "")
        rows.append(ds.group_row(group.name, body))
        r = rows[-1]
        click.echo(f"{group.name}: {r['defects']} defects, error ÷ floor per defect {number(r['per_defect'])}, "
                   f"within ±2σ {percent(r['within_2_sigma'])}, σ ÷ floor {number(r['sigma_over_floor'])}, "
                   f"clear-cut silent PASS {r['silent_pass']} ({time.perf_counter() - start:.0f} s)")
        if against is not None:
            earlier = against / group.name / "depth_eval.json"
            if earlier.is_file():
                try:
                    changes[group.name] = ds.decision_changes(json.loads(earlier.read_text())["rows"], body["rows"])
                except (ValueError, KeyError) as exc:
                    fail(f"{earlier}: cannot be compared with this run's {group.name} ({exc})")
    text = (f"Machine: {machine}; the groups took "
            f"{time.perf_counter() - began:.0f} s.\n\n" + ds.rows_table(rows))
    undecided = ds.undecided_table(rows)
    if undecided:
        text += "\nWhat the undecided defects' uncertainty was mostly made of:\n\n" + undecided
    if against is not None:
        missing = [g.name for g in chosen if g.name not in changes]
        text += (f"\nDecided differently from {against}:\n\n" + ds.changes_table(changes)
                 + (f"\nNot in {against}: {', '.join(missing)}\n" if missing else ""))
    click.echo("\n" + text)
    commands_md = "\n".join(f"- {name}: `{command}`" for name, command in commands.items())
    write_text(out / "suite.md", text + "\nThe commands:\n\n" + commands_md + "\n")
    write_text(out / "suite.json", json.dumps({"suite": str(suite.path), "root": str(root), "machine": machine,
                                               "rows": rows, "against": None if against is None else str(against),
                                               "changes": changes, "commands": commands}, indent=1))
    click.echo(f"wrote {out / 'suite.md'}, {out / 'suite.json'}")


def register(cli: click.Group) -> None:
    cli.commands["eval"].add_command(eval_depth_suite_command, "depth-suite")
