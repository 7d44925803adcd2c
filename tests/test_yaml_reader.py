"""drivers/yaml_reader.py: YAML 1.1's numbers that do not mean what their digits say are refused, and so is a key
given twice."""
from __future__ import annotations

import pytest
import yaml

from drivers.yaml_reader import (MAX_DEPTH, DuplicateKey, Misread, MisreadNumber, StructureError, option_value,
                                  safe_load, safe_load_lines)


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
        assert info.value.described.startswith("a.b.1.d: 011: YAML reads a leading zero as octal")

    def test_a_value_outside_any_mapping_is_described_by_its_problem_alone(self):
        with pytest.raises(MisreadNumber) as info:
            option_value("010")
        assert info.value.key == () and info.value.described == info.value.problem


class TestDuplicateKeys:
    @pytest.mark.parametrize("text, line, key", [
        ("a: 1\nb: 2\na: 3\n", 3, ("a",)),
        ("a:\n  b: [1, {c: 2, 'c': 3}]\n", 2, ("a", "b", 1, "c")),
        ("groups:\n  nine: {sets: [x]}\n  nine: {sets: [y]}\n", 3, ("groups", "nine")),
    ])
    def test_a_key_given_twice_is_refused_with_its_second_line_and_its_path(self, text, line, key):
        # YAML keeps the last without a word: a second threshold would hide the first
        with pytest.raises(DuplicateKey) as info:
            safe_load(text)
        assert (info.value.line, info.value.key) == (line, key)
        assert info.value.described.startswith(f"{'.'.join(map(str, key))}: given twice (first at line ")

    def test_a_merge_may_still_override_what_it_merges(self):
        assert safe_load("m: &m {x: 1}\nn: {<<: *m, x: 2}\n")["n"] == {"x": 2}

    def test_a_list_as_a_key_is_yaml_s_own_error_not_a_traceback(self):
        with pytest.raises(yaml.constructor.ConstructorError, match="unhashable"):
            safe_load("? [1, 2]\n: 3\n")

    def test_safe_load_lines_gives_each_key_s_line(self):
        data, lines = safe_load_lines("a:\n  b: [1, {c: 2}]\nd: 3\n")
        assert data == {"a": {"b": [1, {"c": 2}]}, "d": 3}
        assert lines == {("a",): 1, ("a", "b"): 2, ("a", "b", 0): 2, ("a", "b", 1): 2, ("a", "b", 1, "c"): 2, ("d",): 3}
        assert safe_load_lines("") == (None, {})

    def test_a_command_line_value_with_a_key_twice_is_refused_not_taken_as_text(self):
        with pytest.raises(Misread) as info:
            option_value("{a: 1, a: 2}")
        assert info.value.described.startswith("a: given twice")
        assert option_value("{a: 1") == "{a: 1"  # not YAML: the text itself


class TestStructure:
    def test_anchors_aliases_and_merges_still_read(self):
        text = "m: &m {x: 1}\nn: {<<: *m, y: 2}\nl: [*m, *m]\n"
        assert safe_load(text) == {"m": {"x": 1}, "n": {"x": 1, "y": 2}, "l": [{"x": 1}, {"x": 1}]}

    def test_an_empty_document_is_none(self):
        assert safe_load("") is None and safe_load("# only a comment\n") is None

    @pytest.mark.parametrize("text, line", [("a: &a [*a]\n", 1), ("a:\n  b: &b {c: *b}\n", 2)])
    def test_an_alias_that_holds_itself_is_refused_with_its_line(self, text, line):
        with pytest.raises(StructureError, match="refers to a node that holds it") as info:
            safe_load(text)
        assert info.value.line == line

    def test_aliases_that_expand_beyond_the_limit_are_refused_before_they_are_built(self):
        levels = ["x0: &x0 [1, 2, 3, 4, 5, 6, 7, 8, 9]"]
        levels += [f"x{i}: &x{i} [" + ", ".join([f"*x{i - 1}"] * 9) + "]" for i in range(1, 10)]  # 9^10 values
        with pytest.raises(StructureError, match="expand it beyond 100,000 values"):
            safe_load("\n".join(levels))
        assert len(safe_load("\n".join(levels[:4]))["x3"]) == 9  # 9^4 values: a document that large still reads

    def test_nesting_deeper_than_the_limit_is_refused_with_its_line_not_a_recursion_error(self):
        deep = "a:\n  b: " + "[" * (MAX_DEPTH + 1) + "]" * (MAX_DEPTH + 1) + "\n"
        with pytest.raises(StructureError, match=f"nested deeper than {MAX_DEPTH} levels") as info:
            safe_load(deep)
        assert info.value.line == 2
        assert safe_load("a: " + "[" * (MAX_DEPTH - 1) + "1" + "]" * (MAX_DEPTH - 1))["a"] is not None
        with pytest.raises(StructureError):
            safe_load("a: " + "[" * 5000 + "]" * 5000)

    def test_aliases_that_nest_it_deeper_than_the_limit_are_refused(self):
        half = MAX_DEPTH // 2 + 1
        text = "x: &x " + "[" * half + "1" + "]" * half + "\ny: " + "[" * half + "*x" + "]" * half + "\n"
        with pytest.raises(StructureError, match=f"nest it deeper than {MAX_DEPTH} levels"):
            safe_load(text)
