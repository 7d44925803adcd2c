"""The base of every settings model, the recipe's sections and the plugins' settings alike.

Three rules for what an integrator types: a key the model does not know is an error (a typo is not a
silently ignored setting), so is a number that is not finite (pydantic reads the text ``nan`` as one, and a
rule whose threshold is NaN never rejects), and so is a YAML boolean where a number is expected. Pydantic
takes ``true`` for 1 and ``false`` for 0, so ``unit: false`` addressed every Modbus device on the line (unit
0 is the broadcast), ``address: yes`` pulsed coil 1, and ``threshold: on`` rejected defects deeper than 1 mm.
"""
from __future__ import annotations

import types
from typing import Annotated, Any, Literal, Union, get_args, get_origin

from pydantic import BaseModel, ConfigDict, ValidationInfo, field_validator

# The longest back-off between a device's reconnection attempts (outputs, cameras): a device back on the line
# waits no longer than this to be used again, and a wait too long for the clock (1e300 ms) cannot be set.
MAX_RECONNECT_MS = 60_000.0


def takes_bool(annotation: Any) -> bool:
    """Whether a field of this type may hold ``True`` or ``False`` as a value of its own."""
    if annotation is bool or annotation is Any:
        return True
    origin = get_origin(annotation)
    if origin is Literal:
        return any(isinstance(a, bool) for a in get_args(annotation))
    if origin in (Union, types.UnionType, Annotated):
        return any(takes_bool(a) for a in get_args(annotation))
    return False


def _items_take_bool(annotation: Any) -> bool:
    """For a list or tuple field: whether an item may be a boolean."""
    origin = get_origin(annotation)
    if origin in (Union, types.UnionType, Annotated):
        return any(_items_take_bool(a) for a in get_args(annotation) if a is Any or get_origin(a) in (list, tuple))
    if origin in (list, tuple):
        items = [a for a in get_args(annotation) if a is not Ellipsis]
        return not items or any(takes_bool(a) for a in items)
    return True


class Settings(BaseModel):
    # allow_inf_nan: unquoted YAML such as nan or 1e400 is text, not a YAML float, which pydantic reads as a number
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_boolean_for_a_number(cls, value: Any, info: ValidationInfo) -> Any:
        annotation = cls.model_fields[info.field_name].annotation
        if isinstance(value, bool) and not takes_bool(annotation):
            raise ValueError("a boolean where a number or text is expected (YAML reads true, false, yes, no, on "
                             "and off unquoted as booleans: quote them where text is meant)")
        if isinstance(value, (list, tuple)) and not _items_take_bool(annotation):
            for position, item in enumerate(value):
                if isinstance(item, bool):
                    raise ValueError(f"item {position}: a boolean where a number or text is expected")
        return value
