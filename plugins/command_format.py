"""The text of a part's command in a recipe's format strings (the ``log`` and ``serial`` outputs).

A format names the part's fields in braces: ``{part_id}``, ``{status}`` (PASS, REJECT, ERROR or FLAG),
``{frame_id}``, ``{index}``. A format that names another field, or is not a format at all, is refused
with the recipe, not found out at the first reject.
"""
from __future__ import annotations

from core.types import PartResult

FIELDS = ("part_id", "status", "frame_id", "index")
_EXAMPLE = {"part_id": "P1", "status": "REJECT", "frame_id": "f", "index": 0}


def checked_format(value: str | None) -> str | None:
    """``value`` unchanged where every field it names is one of ``FIELDS``; a ValueError saying which is
    not, or what is wrong with the braces, otherwise. None passes (no command of that kind)."""
    if value is None:
        return None
    try:
        value.format(**_EXAMPLE)
    except KeyError as exc:
        raise ValueError(f"bad format {value!r}: unknown field {{{exc.args[0]}}}; use {known()}") from None
    except (IndexError, ValueError, AttributeError, TypeError) as exc:
        raise ValueError(f"bad format {value!r}: {exc}; use {known()}") from None
    return value


def command_text(fmt: str, part: PartResult) -> str:
    """``fmt`` (a ``checked_format``) filled in with ``part``'s fields."""
    return fmt.format(part_id=part.part_id, status=part.verdict.status.value, frame_id=part.frame_id,
                      index=part.index)


def known() -> str:
    return ", ".join("{" + name + "}" for name in FIELDS)
