"""The evaluation suite: the sets behind the depth figures, the groups they are scored in, one row per group.

``sim/eval_sets.yaml`` names each set (a folder under a root) with the ``inspect sim`` command that renders
it, and each group with its sets and the options of ``inspect eval depth``. ``load_suite`` reads and checks
it; ``group_row`` makes a group's row from its ``depth_eval.json``; ``decision_changes`` says which defects
two runs of a group decided differently, the check of a change to the depth method.
"""
from __future__ import annotations

import difflib
import fnmatch
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from core.report_text import decided, number, percent
from core.uncertainty_budget import tally_words
from drivers.text_files import NotUtf8, decode
from drivers.yaml_reader import Misread, safe_load

SUITE = Path(__file__).resolve().parent.parent / "sim" / "eval_sets.yaml"
RENDERERS = ("generate", "raycast")  # the ``inspect sim`` commands that render an evaluation set


class SuiteError(ValueError):
    """A suite file that cannot be used; the message names the file and the key."""


@dataclass(frozen=True)
class Group:
    name: str
    sets: tuple[str, ...]  # set names, in the file's order
    options: tuple[str, ...]  # ``inspect eval depth`` options


@dataclass(frozen=True)
class Suite:
    path: Path
    sets: dict[str, tuple[str, ...]]  # set name -> ``inspect sim`` arguments (its folder not yet added)
    groups: dict[str, Group]

    def render_args(self, name: str, root: Path) -> list[str]:
        """The ``inspect`` arguments that render set ``name`` into its folder under ``root``."""
        command, *options = self.sets[name]
        return ["sim", command, str(root / name), *options]

    def chosen(self, names: list[str] | tuple[str, ...]) -> list[Group]:
        """The groups ``names`` (all, in the file's order, if none); SuiteError with a "did you mean" for a
        name the file does not hold."""
        for name in names:
            if name not in self.groups:
                close = difflib.get_close_matches(name, list(self.groups), n=1, cutoff=0.6)
                raise SuiteError(f"{self.path}: no group {name!r}" + (f"; did you mean {close[0]!r}?" if close else
                                 f" (groups: {', '.join(self.groups)})"))
        return [g for g in self.groups.values() if not names or g.name in names]


def load_suite(path: Path = SUITE) -> Suite:
    """The suite file at ``path``, checked: every set rendered by an ``inspect sim`` command that renders a
    set, every group's sets among the file's (``folder/*``: every set of that folder, which must hold one),
    every command line one that splits into words. SuiteError naming the file and the key otherwise."""
    path = Path(path)
    try:
        data = safe_load(decode(path.read_bytes()))
    except OSError as exc:
        raise SuiteError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    except NotUtf8 as exc:
        raise SuiteError(f"{path}: line {exc.line}: {exc}") from None
    except Misread as exc:  # a key given twice (a second group of one name), a number YAML misreads
        raise SuiteError(f"{path}: line {exc.line}: {exc.described}") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f"line {mark.line + 1}: " if mark is not None else ""
        raise SuiteError(f"{path}: {at}not YAML ({getattr(exc, 'problem', None) or exc})") from None
    if not isinstance(data, dict) or set(data) != {"sets", "groups"}:
        raise SuiteError(f"{path}: expected the two mappings sets: and groups:, got "
                         f"{sorted(data) if isinstance(data, dict) else type(data).__name__}")
    for key in ("sets", "groups"):
        if not isinstance(data[key], dict) or not data[key]:
            raise SuiteError(f"{path}: {key}: expected a mapping of names")
    sets = {}
    for name, command in data["sets"].items():
        where = f"{path}: sets.{name}"
        if not isinstance(name, str) or not name or Path(name).is_absolute() or ".." in Path(name).parts:
            raise SuiteError(f"{where}: a set's name is a folder under the suite's root")
        words = _words(command, where)
        if not words or words[0] not in RENDERERS:
            raise SuiteError(f"{where}: expected an `inspect sim` command that renders a set ({' or '.join(RENDERERS)}"
                             f" and its options), got {command!r}")
        sets[name] = tuple(words)
    groups = {}
    for name, body in data["groups"].items():
        where = f"{path}: groups.{name}"
        if not isinstance(body, dict) or not set(body) <= {"sets", "options"} or "sets" not in body:
            raise SuiteError(f"{where}: expected {{sets: [...], options: ...}}")
        if not isinstance(body["sets"], list) or not body["sets"]:
            raise SuiteError(f"{where}.sets: expected a list of set names")
        members = []
        for pattern in body["sets"]:
            found = [s for s in sets if fnmatch.fnmatchcase(s, str(pattern))] if isinstance(pattern, str) else []
            if not found:
                close = difflib.get_close_matches(str(pattern), list(sets), n=1, cutoff=0.6)
                raise SuiteError(f"{where}.sets: {pattern!r} is none of the file's sets"
                                 + (f"; did you mean {close[0]!r}?" if close else ""))
            members += [s for s in found if s not in members]
        options = _words(body.get("options") or "", f"{where}.options")
        groups[str(name)] = Group(str(name), tuple(members), tuple(options))
    return Suite(path, sets, groups)


def _words(text: Any, where: str) -> list[str]:
    if not isinstance(text, str):
        raise SuiteError(f"{where}: expected a command line, got {text!r}")
    try:
        return shlex.split(text)
    except ValueError as exc:
        raise SuiteError(f"{where}: {exc} in {text!r}") from None


def is_rendered(folder: Path) -> bool:
    """Whether ``folder`` holds a rendered set: its calibration and at least one frame's labels (a render that
    fails removes what it wrote)."""
    return (folder / "calib.yaml").is_file() and any((folder / "labels").glob("*.json"))


def group_row(name: str, body: dict) -> dict[str, Any]:
    """A group's row from its ``depth_eval.json`` (``body``): the depth method's figures over all its sets."""
    s = body["all"]["measurement"]
    proven_pass, undecided_pass, proven_reject, undecided_reject = decided(s.get("confusion", {}))
    return {
        "group": name,
        "defects": s["defects"],
        "measured": s["measured"],
        "error_mm": s.get("deviation_error_mm", {}),
        "error_over_floor": s.get("error_over_floor", {}),
        "per_defect": s.get("error_over_floor_per_defect"),
        "ratio": s.get("ratio_median"),
        "within_2_sigma": s.get("within_2_sigma"),
        "sigma_over_floor": s.get("sigma_over_floor_median"),
        "texture_per_defect": s.get("error_over_texture_floor_per_defect"),
        "texture_sigma": s.get("sigma_over_texture_floor_median"),
        # each part's share of the error's squares (core/error_parts.py), where the sets have a true disparity
        "parts": {name: part["share"] for name, part in (s.get("error_parts") or {}).items()
                  if isinstance(part, dict)},
        "distance_percent": s.get("distance_error_percent", {}).get("median"),
        "distance_within_2_sigma": s.get("distance_within_2_sigma"),
        "distance_per_defect": s.get("distance_over_floor_per_defect"),
        "silent_pass": s.get("clear_cut_silent_pass", 0),
        "proven_pass": proven_pass,
        "undecided_pass": undecided_pass,
        "proven_reject": proven_reject,
        "undecided_reject": undecided_reject,
        # the undecided by the largest part of their uncertainty (core/uncertainty_budget.py) and true outcome
        "undecided_from": s.get("undecided_from", {}),
    }


def _parts(shares: dict[str, float] | None) -> str:
    """The error's parts' shares as "9 / 90 / 1 %" in the summary's order (ring, region, extent: the column's header),
    or n/a without a true disparity (or without an error)."""
    if not shares or any(share is None for share in shares.values()):
        return "n/a"
    return " / ".join(f"{100 * share:.0f}" for share in shares.values()) + " %"


def rows_table(rows: list[dict[str, Any]]) -> str:
    """The groups' rows as a Markdown table."""
    lines = ["| group | defects (measured) | deviation error mm, median / p90 | error ÷ floor, median / p90 | "
             "per defect | measured ÷ true | within ±2σ | σ ÷ floor | texture's floor: per defect, σ | "
             "the error's parts: ring / region's estimate / region's extent | "
             "distance error, median % of Z (within ±2σ) | "
             "distance ÷ floor per defect | clear-cut silent PASS | good parts proven / undecided | "
             "beyond the limit proven / undecided |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        e, q = r["error_mm"], r["error_over_floor"]
        lines.append(
            f"| {r['group']} | {r['defects']} ({r['measured']}) | {number(e.get('median'), 3)} / {number(e.get('p90'), 3)} | "
            f"{number(q.get('median'))} / {number(q.get('p90'))} | {number(r['per_defect'])} | {number(r['ratio'])} | "
            f"{percent(r['within_2_sigma'])} | {number(r['sigma_over_floor'])} | "
            f"{number(r['texture_per_defect'])}, {number(r['texture_sigma'])} | {_parts(r.get('parts'))} | "
            f"{number(r['distance_percent'], 3)} "
            f"({percent(r['distance_within_2_sigma'])}) | {number(r['distance_per_defect'])} | {r['silent_pass']} | "
            f"{r['proven_pass']} / {r['undecided_pass']} | {r['proven_reject']} / {r['undecided_reject']} |")
    return "\n".join(lines) + "\n"


UNDECIDED_SHOWN = 3  # parts of the uncertainty named per group, most often the largest first


def undecided_table(rows: list[dict[str, Any]]) -> str:
    """Per group, what its undecided defects' uncertainty was mostly made of (``undecided_from``): the parts that were
    the largest most often, each with its count inside the limit / beyond it; '' where no group has any."""
    kept = [r for r in rows if r.get("undecided_from")]
    if not kept:
        return ""
    lines = ["| group | undecided, inside the limit / beyond it | the largest part of their uncertainty "
             "(inside / beyond), most often first |", "|---|---|---|"]
    for r in kept:
        words = tally_words(r["undecided_from"])
        named = "; ".join(words[:UNDECIDED_SHOWN])
        more = len(words) - UNDECIDED_SHOWN
        lines.append(f"| {r['group']} | {r['undecided_pass']} / {r['undecided_reject']} | {named}"
                     f"{f'; {more} more' if more > 0 else ''} |")
    return "\n".join(lines) + "\n"


def decision_changes(before: list[dict], after: list[dict]) -> dict[str, int]:
    """How the defects of two runs of one group (their ``depth_eval.json`` rows, the same defects in any
    order) were decided differently: good parts and parts beyond a limit no longer or newly proven; in each run
    the defects proven on the wrong side of their limit, however near it, and of those the clear-cut parts beyond
    a limit proven inside it (a silent PASS). ValueError where the rows are not the same defects."""
    def by_defect(rows):
        return {(r["sequence"], r["frame_id"], tuple(r["box"])): r for r in rows}

    earlier, later = by_defect(before), by_defect(after)
    if earlier.keys() != later.keys() or len(earlier) != len(before) or len(later) != len(after):
        raise ValueError("the two runs did not measure the same defects (other sets)")
    change = dict.fromkeys(("good_lost", "good_gained", "beyond_lost", "beyond_gained", "wrong_before", "wrong_after",
                            "silent_before", "silent_after"), 0)
    for key, a in earlier.items():
        b = later[key]
        proven = a["true_status"] if a["true_status"] in ("PASS", "REJECT") else None
        side = "good" if a["true_status"] == "PASS" else "beyond"
        if proven is not None:
            change[f"{side}_lost"] += a["proven"] == proven and b["proven"] != proven
            change[f"{side}_gained"] += a["proven"] != proven and b["proven"] == proven
        for run, row in (("before", a), ("after", b)):
            # a change that proves a defect on the wrong side is one to look at even where it lies near its limit:
            # the guard band is all that keeps such a defect undecided
            wrong = {"PASS": "REJECT", "REJECT": "PASS"}.get(row["true_status"]) == row["proven"]
            change[f"wrong_{run}"] += wrong
            change[f"silent_{run}"] += wrong and row["true_status"] == "REJECT" and bool(row["clear_cut"])
    return change


def changes_table(changes: dict[str, dict[str, int]]) -> str:
    """Per group, ``decision_changes`` as a Markdown table."""
    lines = ["| group | good parts no longer proven | good parts newly proven | beyond the limit no longer proven | "
             "beyond the limit newly proven | proven on the wrong side before → after | clear-cut silent PASS before → "
             "after |",
             "|---|---|---|---|---|---|---|"]
    for name, c in changes.items():
        lines.append(f"| {name} | {c['good_lost']} | {c['good_gained']} | {c['beyond_lost']} | {c['beyond_gained']} | "
                     f"{c['wrong_before']} → {c['wrong_after']} | {c['silent_before']} → {c['silent_after']} |")
    return "\n".join(lines) + "\n"
