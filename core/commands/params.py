"""Option types the commands share."""
from __future__ import annotations

import math
import re
from pathlib import Path

import click


class Finite(click.FloatRange):
    """A float (in an optional range) that is a number: ``nan`` passes every range check, since every
    comparison with it is false, and ``inf`` is no search range, distance or delay."""

    name = "float"

    def convert(self, value, param, ctx):
        number = super().convert(value, param, ctx)
        if not math.isfinite(number):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return number

    def _describe_range(self) -> str:
        # click writes an unbounded range as "x<=None" in the help
        return "finite" if self.min is None and self.max is None else super()._describe_range()


FINITE = Finite()


def cuda_if_present(ctx, param, value):
    """``--device``: ``auto``, ``cpu``, or ``cuda`` (``cuda:N``) only where torch sees that CUDA device. A plugin
    asked for ``auto`` runs on the CPU without one, so a map or a benchmark said to be a GPU's would silently be
    the CPU's; any other name reached the detector, and every part was an ERROR."""
    if value is None or value in ("auto", "cpu"):
        return value
    match = re.fullmatch(r"cuda(?::(\d+))?", str(value))
    if match is None:
        raise click.BadParameter(f"{value!r}: one of auto, cpu, cuda or cuda:N", ctx=ctx, param=param)
    from core.devices import cuda_problem

    if (problem := cuda_problem()) is not None:
        raise click.BadParameter(problem, ctx=ctx, param=param)
    if match.group(1) is not None and (problem := cuda_problem(int(match.group(1)))) is not None:
        raise click.BadParameter(f"{value!r}: {problem}", ctx=ctx, param=param)
    return value


def demo_recipe() -> Path:
    """The demo recipe of the checkout this package runs from, so that a command works from any folder;
    ``recipes/steel_plate.yaml`` of the working folder where the package was installed without it."""
    beside = Path(__file__).resolve().parents[2] / "recipes" / "steel_plate.yaml"
    return beside if beside.is_file() else Path("recipes/steel_plate.yaml")


def make_folder(path: Path) -> str | None:
    """Make the output folder ``path`` (and its parents); why it cannot be, in one line, else None. Made
    before the work, so that it is said then (a ten-minute evaluation), not as a traceback after it."""
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        return f"{path}: cannot create the folder ({exc.strerror})"
    return None


def out_folder(ctx: click.Context, param: click.Parameter, value: Path | None) -> Path | None:
    """Click callback for an output folder: ``make_folder`` as the option is read."""
    problem = None if value is None else make_folder(value)
    if problem is not None:
        raise click.BadParameter(problem, ctx, param)
    return value


def out_file(ctx: click.Context, param: click.Parameter, value: Path | None) -> Path | None:
    """Click callback for an output file: its folder made now (``out_folder``)."""
    if value is not None:
        out_folder(ctx, param, value.parent)
    return value


def overwritten_input(outputs: dict[str, Path | None], inputs: list[Path]) -> str | None:
    """Why writing the command's ``outputs`` (option -> path, None where not given) would destroy what it reads
    (one of ``inputs``, or another output, the same file however it is named), in one line, or None."""
    read = {path.resolve(): path for path in inputs}
    written: dict[Path, str] = {}
    for option, path in outputs.items():
        if path is None:
            continue
        target = path.resolve()
        if target in read:
            named = "" if str(read[target]) == str(path) else f" (as {read[target]})"
            return f"{option} {path}: the command reads that file{named}: writing it would destroy it"
        if target in written:
            return f"{option} {path}: {written[target]} writes that file too"
        written[target] = option
    return None
