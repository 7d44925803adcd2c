"""Where a defect's uncertainty comes from, in words (``core.uncertainty_budget``)."""
from __future__ import annotations

import numpy as np
import pytest

from core.types import UncertaintyPart
from core.uncertainty_budget import KINDS, cause_clause, kind_name, largest, largest_kind, shift_words


def _part(cause: str, variance: float, kind: str = "noise") -> UncertaintyPart:
    return UncertaintyPart(kind, cause, variance)


class TestShiftWords:
    def test_rows_then_columns_rounded_to_pixels(self):
        assert shift_words(3.2, -12.6) == "13 px up and 3 px right"
        assert shift_words(-7.0, 4.0) == "4 px down and 7 px left"

    def test_a_shift_along_one_axis_names_that_one(self):
        assert shift_words(0.3, 9.0) == "9 px down"
        assert shift_words(-6.0, -0.2) == "6 px left"

    def test_numpy_values_as_the_box_arithmetic_gives_them(self):
        assert shift_words(np.float64(-2.0), np.float64(5.0)) == "5 px down and 2 px left"

    def test_less_than_half_a_pixel_is_in_place(self):
        assert shift_words(0.4, -0.4) == "in place"


class TestLargest:
    def test_the_part_with_most_variance_and_its_share(self):
        part, share = largest([_part("a", 1.0), _part("b", 3.0, "moved")])
        assert (part.kind, part.cause) == ("moved", "b") and share == pytest.approx(0.75)

    def test_the_first_of_equals(self):
        assert largest([_part("a", 2.0), _part("b", 2.0)])[0].cause == "a"

    @pytest.mark.parametrize("parts", [[], [_part("a", 0.0)], [_part("a", float("nan"))], [_part("a", float("inf"))]])
    def test_none_without_a_variance_to_share(self, parts):
        assert largest(parts) is None


class TestLargestKind:
    def test_the_kind_of_the_largest_part(self):
        assert largest_kind([_part("a", 1.0, "surface"), _part("b", 3.0, "moved")]) == "moved"

    @pytest.mark.parametrize("parts", [[], [_part("a", 0.0)]])
    def test_empty_without_a_variance_to_share(self, parts):
        assert largest_kind(parts) == ""


class TestKindName:
    def test_a_kind_by_its_tally_name_and_an_unknown_one_as_it_is(self):
        assert kind_name("moved") == KINDS["moved"] and kind_name("ring_side") == "ring_side"


class TestCauseClause:
    def test_names_the_largest_with_its_share(self):
        parts = [_part("placing the surface around the box", 0.01, "surface"),
                 _part("the region moved 12 px down, which reads 1.60 mm", 0.49, "moved")]
        assert cause_clause(parts) == "its uncertainty: 98 % from the region moved 12 px down, which reads 1.60 mm"

    def test_empty_where_there_is_no_account(self):
        assert cause_clause([]) == ""


def test_every_kind_has_a_name_for_tallies():
    assert all(isinstance(name, str) and name for name in KINDS.values())
    assert {"surface", "noise", "moved", "interior"} <= set(KINDS)
