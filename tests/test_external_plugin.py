"""The promise "add a new detector without forking": a separate package, installed by pip,
found through the entry-point group, selected by name in a recipe, run by `inspect run`."""
from __future__ import annotations

import sqlite3

from conftest import cli, write_recipe

RECIPE = """\
name: external
camera:
  plugin: replay
  settings: {{path: seq}}
stereo:
  backend: opencv_sgbm
  working_distance_mm: [300, 600]
detector:
  plugin: fixed_roi
  settings:
    regions:
      - {{name: weld_seam, box: {box}}}
decision:
  rules:
    - {{class: weld_seam, quantity: deviation_mm, op: ">", threshold: 1.5}}
outputs:
  - plugin: log
    settings: {{file: rejects.log}}
results:
  path: results
"""


def test_listed_with_its_package(external_plugin_site):
    result = cli("plugins", env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert result.returncode == 0, result.stderr
    line = next(l for l in result.stdout.splitlines() if l.strip().startswith("fixed_roi"))
    assert "stereo-inspect-fixed-roi 0.2.0" in line
    assert "replay" in result.stdout and "stereo-inspect 0.1.0" in result.stdout


def test_not_found_without_the_package(tmp_path, plane_sequence):
    info = plane_sequence([0.0])
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"]))
    result = cli("validate", str(path))
    assert result.returncode == 2 and "unknown detector plugin 'fixed_roi'" in result.stderr


def test_selected_by_name_and_run(tmp_path, plane_sequence, external_plugin_site):
    info = plane_sequence([0.0, 6.0])
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"]))
    result = cli("run", str(path), env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert result.returncode == 0, result.stdout + result.stderr
    assert "weld_seam" in result.stdout and "parts 2  passed 1  rejected 1  errors 0" in result.stdout
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    assert [r[0] for r in db.execute("SELECT class FROM defects")] == ["weld_seam", "weld_seam"]
    log = (tmp_path / "rejects.log").read_text().splitlines()
    assert len(log) == 1 and log[0].endswith("REJECT R1-000001 REJECT")
