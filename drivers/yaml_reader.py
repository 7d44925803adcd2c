"""Safe YAML that refuses the YAML 1.1 numbers which do not mean what they look like.

PyYAML reads YAML 1.1, where ``010`` is octal (8) and ``1:30`` is base 60 (90). In a recipe those are a
Modbus address or a time an integrator wrote in decimal: coil 8 pulsed instead of coil 10, and the reject
lost at the wrong gate; in a calibration file a baseline of ``0120`` mm read as 80. Such a scalar is an
error naming its line; quoted, or written without the leading zero, it is whatever the key expects.

A mapping that gives a key twice, which YAML reads as the last without a word, is an error naming the
second one's line: a recipe's second threshold must not hide its first, nor a calibration file's second focal
length its first, nor an evaluation suite's second group of one name its first.

A document no reader could walk is an error naming its line too: an alias that refers to a node holding
it (``a: &a [*a]``), aliases that expand the document to more than ``MAX_NODES`` values (a "billion laughs"),
and nesting deeper than ``MAX_DEPTH`` levels (PyYAML's composer, and every reader of a recipe after it,
recurse once per level).

This module imports nothing from the rest of stereo-inspect.
"""
from __future__ import annotations

import re
from typing import Any

import yaml

MAX_NODES = 100_000  # values after expanding aliases: a recipe holds a few hundred
MAX_DEPTH = 100  # levels of nesting, aliases expanded: a recipe nests five
_OCTAL = re.compile(r"[-+]?0[0-7_]+")
_BASE_60 = re.compile(r"[-+]?[0-9][0-9_]*(:[0-5]?[0-9])+(\.[0-9_]*)?")


class Misread(yaml.MarkedYAMLError):
    """A document YAML would read otherwise than it is written: ``MisreadNumber`` or ``DuplicateKey``. ``line``
    is 1-based, ``key`` the path of mapping keys and list indexes to the value."""
    line: int
    key: tuple[str | int, ...]

    @property
    def described(self) -> str:
        """``dotted.key: problem``, or the problem alone for a value outside any mapping or list."""
        return f"{'.'.join(map(str, self.key))}: {self.problem}" if self.key else str(self.problem)


class MisreadNumber(Misread):
    """A scalar YAML 1.1 reads as another number than its digits say; ``line`` is 1-based, ``key`` the path
    of the mapping keys and list indexes to it."""

    def __init__(self, mark: yaml.Mark, text: str, why: str):
        super().__init__(problem=f"{text}: {why}", problem_mark=mark)
        self.line = mark.line + 1
        self.key: tuple[str | int, ...] = ()


def given_twice(first: int) -> str:
    """What a key given a second time is told, ``first`` the line (1-based) of its first."""
    return f"given twice (first at line {first}); one of them would be ignored"


class StructureError(yaml.MarkedYAMLError):
    """An alias that contains itself, aliases that expand the document beyond ``MAX_NODES`` values, or nesting
    deeper than ``MAX_DEPTH`` levels."""

    def __init__(self, mark: yaml.Mark, why: str):
        super().__init__(problem=why, problem_mark=mark)
        self.line = mark.line + 1


class DuplicateKey(Misread):
    """A mapping that gives a key twice, which YAML reads as the last silently; ``line`` is the second one's
    (1-based), ``key`` the path of mapping keys and list indexes to it."""

    def __init__(self, mark: yaml.Mark, key: tuple[str | int, ...], first: int):
        super().__init__(problem=given_twice(first), problem_mark=mark)
        self.line = mark.line + 1
        self.key = key


class _Loader(yaml.SafeLoader):
    _depth = 0  # collections open while composing

    def compose_node(self, parent, index):
        # the composer recurses once per level: refused with its line before Python's recursion limit ends it
        # in a traceback
        opens = int(self.check_event(yaml.SequenceStartEvent, yaml.MappingStartEvent))
        if opens and self._depth >= MAX_DEPTH:
            raise StructureError(self.peek_event().start_mark, f"nested deeper than {MAX_DEPTH} levels")
        self._depth += opens
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= opens

    def construct_yaml_int(self, node):
        text = self.construct_scalar(node)
        try:
            value = super().construct_yaml_int(node)
        except ValueError:  # more digits than Python converts (sys.get_int_max_str_digits)
            raise MisreadNumber(node.start_mark, f"{text[:12]}...", f"an integer of {len(text)} digits, more than "
                                f"can be read; no setting takes a number that long") from None
        decimal = int(text.replace("_", ""), 10) if _OCTAL.fullmatch(text) else value
        if decimal != value:
            raise MisreadNumber(node.start_mark, text, f"YAML reads a leading zero as octal, {value}; write {decimal} "
                                f"without the zero ({value} if octal was meant), or quote it if it is text")
        if _BASE_60.fullmatch(text):
            raise MisreadNumber(node.start_mark, text, f"YAML reads this as the base-60 number {value}; write the "
                                f"number, or quote it if it is text")
        return value

    def construct_yaml_float(self, node):
        text = self.construct_scalar(node)
        value = super().construct_yaml_float(node)
        if _BASE_60.fullmatch(text):
            raise MisreadNumber(node.start_mark, text, f"YAML reads this as the base-60 number {value:g}; write the "
                                f"number, or quote it if it is text")
        return value


_Loader.add_constructor("tag:yaml.org,2002:int", _Loader.construct_yaml_int)
_Loader.add_constructor("tag:yaml.org,2002:float", _Loader.construct_yaml_float)


def _path_to(node: yaml.Node, index: int, path: tuple = ()) -> tuple | None:
    """The keys and list indexes from ``node`` to the scalar that starts at character ``index``."""
    if isinstance(node, yaml.ScalarNode):
        return path if node.start_mark.index == index else None
    children = (node.value if isinstance(node, yaml.MappingNode) else
                [(None, item) for item in node.value] if isinstance(node, yaml.SequenceNode) else [])
    for position, (key, value) in enumerate(children):
        found = _path_to(value, index, path + (key.value if key is not None else position,))
        if found is not None:
            return found
    return None


def _check_expansion(node: yaml.Node) -> None:
    """``StructureError`` where a node holds itself, or the document with its aliases expanded passes
    MAX_NODES values or MAX_DEPTH levels. The walk follows aliases as the document's readers will, on a stack
    of its own, and stops at the limits, so a bomb costs no more."""
    count, holding = 0, set()  # holding: the nodes on the way down to the one visited
    stack = [(node, 0, False)]
    while stack:
        item, depth, leaving = stack.pop()
        if leaving:
            holding.discard(id(item))
            continue
        count += 1
        if count > MAX_NODES:
            raise StructureError(item.start_mark, f"the document's aliases (*name) expand it beyond {MAX_NODES:,} "
                                 f"values")
        if depth > MAX_DEPTH:
            raise StructureError(item.start_mark, f"the document's aliases (*name) nest it deeper than {MAX_DEPTH} "
                                 f"levels")
        if isinstance(item, yaml.ScalarNode):
            continue
        if id(item) in holding:
            raise StructureError(item.start_mark, "an alias (*name) refers to a node that holds it: the value would "
                                 "contain itself without end")
        holding.add(id(item))
        stack.append((item, depth, True))
        for child in reversed(item.value):
            for part in reversed(child) if isinstance(child, tuple) else (child,):
                stack.append((part, depth + 1, False))


def safe_load(text: str):
    """``safe_load_lines``'s document alone."""
    return safe_load_lines(text)[0]


def safe_load_lines(text: str) -> tuple[Any, dict[tuple[str | int, ...], int]]:
    """``yaml.safe_load`` of ``text``, with the 1-based line of every key (and list item) by its path of mapping
    keys and list indexes. Raises ``MisreadNumber`` where YAML 1.1 would misread a number, ``DuplicateKey`` where
    a mapping gives a key twice, and ``StructureError`` for a document no reader could walk (an alias that holds
    itself, aliases that expand it without bound, nesting deeper than MAX_DEPTH)."""
    loader = _Loader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None, {}
        _check_expansion(node)
        lines = _key_lines(node)  # DuplicateKey where a mapping gives a key twice
        return loader.construct_document(node), lines
    except MisreadNumber as exc:
        exc.key = _path_to(yaml.compose(text, Loader=yaml.SafeLoader), exc.problem_mark.index) or ()
        raise
    finally:
        loader.dispose()


def _key_lines(root: yaml.Node) -> dict[tuple[str | int, ...], int]:
    """Each key's line (``safe_load_lines``) of a composed document whose aliases ``_check_expansion`` has
    bounded; ``DuplicateKey`` where a mapping gives a key twice."""
    lines: dict[tuple[str | int, ...], int] = {}
    stack: list[tuple[yaml.Node, tuple[str | int, ...]]] = [(root, ())]
    while stack:
        node, path = stack.pop()
        if isinstance(node, yaml.MappingNode):
            for key_node, value_node in node.value:
                if not isinstance(key_node, yaml.ScalarNode):
                    continue  # a list or mapping as a key: the constructor refuses it, naming its line
                child = path + (key_node.value,)
                if child in lines:
                    raise DuplicateKey(key_node.start_mark, child, lines[child])
                lines[child] = key_node.start_mark.line + 1
                stack.append((value_node, child))
        elif isinstance(node, yaml.SequenceNode):
            for index, item in enumerate(node.value):
                lines[path + (index,)] = item.start_mark.line + 1
                stack.append((item, path + (index,)))
    return lines


def option_value(raw: str):
    """The VALUE of a command line's ``KEY=VALUE``: YAML, so that ``3``, ``true`` and ``[1, 2]`` are what they
    look like, or the text itself where it is not YAML; ``Misread`` where YAML would misread a number or a
    mapping gives a key twice."""
    try:
        return safe_load(raw)
    except Misread:
        raise
    except yaml.YAMLError:
        return raw
