"""Option types the commands share."""
from __future__ import annotations

import math

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


FINITE = Finite()
