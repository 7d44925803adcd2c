"""drivers/yaml_reader.py: YAML 1.1's numbers that do not mean what their digits say are refused."""
from __future__ import annotations

import pytest

from drivers.yaml_reader import MisreadNumber, safe_load


class TestSafeLoad:
    @pytest.mark.parametrize("text, value", [
        ("0", 0), ("00", 0), ("07", 7), ("-07", -7), ("10", 10), ("1_000", 1000), ("0x10", 16), ("0.10", 0.1),
        ("08", "08"), ("'010'", "010"), ("1e3", "1e3"), ("[350, 500]", [350, 500]), ("12:00 h", "12:00 h"),
    ])
    def test_numbers_that_read_as_they_look(self, text, value):
        assert safe_load(f"a: {text}") == {"a": value}

    @pytest.mark.parametrize("text, says", [
        ("010", "010: YAML reads a leading zero as octal, 8; write 10 without the zero (8 if octal was meant), or quote "
                "it if it is text"),
        ("-010", "-010: YAML reads a leading zero as octal, -8; write -10"),
        ("0_10", "0_10: YAML reads a leading zero as octal, 8; write 10"),
        ("1:30", "1:30: YAML reads this as the base-60 number 90; write the number, or quote it if it is text"),
        ("1:30.5", "1:30.5: YAML reads this as the base-60 number 90.5"),
        ("12:00:00", "12:00:00: YAML reads this as the base-60 number 43200"),
    ])
    def test_numbers_yaml_misreads_are_refused(self, text, says):
        with pytest.raises(MisreadNumber) as info:
            safe_load(f"a: {text}")
        assert info.value.problem == says or info.value.problem.startswith(says)

    def test_names_the_line_and_the_key_path(self):
        with pytest.raises(MisreadNumber) as info:
            safe_load("a:\n  b: [1, {c: 2, d: 011}]\n")
        assert info.value.line == 2 and info.value.key == ("a", "b", 1, "d")
