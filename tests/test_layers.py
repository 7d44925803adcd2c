"""The design's layering, read from the source: core never imports a plugin, drivers import nothing of the project."""
from __future__ import annotations

import ast

import pytest
from conftest import ROOT

PROJECT = ("core", "plugins", "drivers", "sim")


def imported(path) -> set[str]:
    """The top-level packages a module imports, at any depth (imports inside functions included)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("layer, forbidden", [("core", {"plugins"}), ("drivers", set(PROJECT) - {"drivers"})])
def test_a_layer_imports_nothing_it_must_not(layer, forbidden):
    offenders = {str(p.relative_to(ROOT)): sorted(imported(p) & forbidden) for p in (ROOT / layer).rglob("*.py")}
    assert not {k: v for k, v in offenders.items() if v}


def test_the_check_sees_an_import_inside_a_function(tmp_path):
    module = tmp_path / "m.py"
    module.write_text("def f():\n    from plugins.replay_camera import ReplayCamera\n")
    assert "plugins" in imported(module)
