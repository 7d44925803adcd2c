"""Where a defect's uncertainty comes from, said so that an integrator can act on it.

A surface measurement's deviation variance is a sum (``core.depth``): the surface around the box, the sensor's
noise over the region's texture, and what the engine adds where the images show that the region may not be what
it seems (its cells disagree, it may hold a wall, one eye sees a sheen the other does not, a copy of it moved
within the box reads farther from the surface). When a rule cannot decide, the largest of them says what would
help: more light or texture, a detector whose boxes hold their defects, boxes that follow a groove.
"""
from __future__ import annotations

from collections.abc import Sequence

from core.types import UncertaintyPart

# each term of a surface measurement's variance by its kind (``UncertaintyPart.kind``): its name in a tally over
# many defects
KINDS = {
    "surface": "placing the surface around the box",
    "noise": "the sensor's noise over the region's texture",
    "scatter": "cells scattering beyond their noise",
    "wall": "a wall the region may hold",
    "unshared": "contrast one eye alone sees",
    "uneven": "a floor not flat over the region",
    "weighting": "textured cells reading otherwise",
    "band": "a band across the region",
    "along_edges": "a band along the region's edges",
    "patch": "the region's centre",
    "moved": "the region moved within its box",
    "interior": "an interior with little texture",
}


def shift_words(dx: float, dy: float) -> str:
    """A shift in the image (px, v down) in words: ``"12 px down and 3 px left"``; ``"in place"`` for less than
    half a pixel either way."""
    words = [f"{abs(d):.0f} px {(neg, pos)[bool(d > 0)]}" for d, neg, pos in ((dy, "up", "down"), (dx, "left", "right"))
             if abs(d) >= 0.5]
    return " and ".join(words) or "in place"


def largest(parts: Sequence[UncertaintyPart]) -> tuple[UncertaintyPart, float] | None:
    """The part with the most variance and its share of the whole (0-1); None where there is no variance (no
    parts, or all of them 0) or it is not a number."""
    total = sum(p.variance_mm2 for p in parts)
    if not parts or not total > 0 or total == float("inf"):
        return None
    part = max(parts, key=lambda p: p.variance_mm2)
    return part, part.variance_mm2 / total


def largest_kind(parts: Sequence[UncertaintyPart]) -> str:
    """The kind of ``largest``'s part; '' where there is none (no account, or nothing in it)."""
    found = largest(parts)
    return "" if found is None else found[0].kind


def kind_name(kind: str) -> str:
    """A kind's name in a tally (``KINDS``), the kind itself where it has none."""
    return KINDS.get(kind, kind)


def tally_words(tally: dict[str, dict[str, int]]) -> list[str]:
    """Defects by the kind of their largest part and their true outcome (``PASS``: inside the limit, ``REJECT``:
    beyond it), as ``"<kind's name> inside / beyond"``, the kinds that count most first."""
    order = sorted(tally, key=lambda k: -sum(tally[k].values()))
    return [f"{kind_name(k)} {tally[k].get('PASS', 0)} / {tally[k].get('REJECT', 0)}" for k in order]


def cause_clause(parts: Sequence[UncertaintyPart]) -> str:
    """``"its uncertainty: 75 % from <cause>"`` for the largest of ``parts``; '' where there is none."""
    found = largest(parts)
    if found is None:
        return ""
    part, share = found
    return f"its uncertainty: {100 * share:.0f} % from {part.cause}"
