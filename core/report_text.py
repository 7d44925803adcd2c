"""How the evaluation reports write a figure that may be missing: ``inspect eval depth``'s tables and
``inspect eval depth-suite``'s rows alike (kept free of torch, which the suite's command must not load)."""
from __future__ import annotations


def number(value: float | None, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def percent(share: float | None) -> str:
    """A share (0..1) as a whole percentage."""
    return "n/a" if share is None else f"{100 * share:.0f} %"


def decided(confusion: dict[str, dict[str, int]]) -> tuple[int, int, int, int]:
    """A summary's decisions against the truth (``confusion``: true status -> what was proven -> count) as the reports'
    columns give them: inside the limit proven / undecided, beyond it proven / undecided."""
    inside, beyond = confusion.get("PASS", {}), confusion.get("REJECT", {})
    return inside.get("PASS", 0), inside.get("undecided", 0), beyond.get("REJECT", 0), beyond.get("undecided", 0)
