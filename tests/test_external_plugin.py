"""The promise "add a new detector without forking": a separate package, installed by pip,
found through the entry-point group, selected by name in a recipe, run by `inspect run`."""
from __future__ import annotations

import json
import shutil
import sqlite3

import pytest
import yaml
from conftest import ROOT, cli, write_recipe

from core.contracts import PluginSpec
from core.hookspecs import hookimpl
from core.registry import PluginConflict, Registry, UnknownPlugin, make_manager

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


def test_the_demo_recipe_in_a_third_party_detectors_boxes_measures_as_the_evaluation_does(tmp_path, external_plugin_site):
    """A user who checks depth by handing the true boxes to ``inspect run`` through a detector of their own gets
    the figures ``inspect eval depth`` reports for the same frame: one engine, not a second path for evaluation."""
    source = ROOT / "sim_fixtures" / "plates_textured"
    seq = tmp_path / "seq"
    for folder, name in (("left", "000001.jpg"), ("right", "000001.jpg"), ("labels", "000001.json"), ("gt", "000001.png")):
        (seq / folder).mkdir(parents=True)
        shutil.copy(source / folder / name, seq / folder / name)
    shutil.copy(source / "calib.yaml", seq / "calib.yaml")
    truth = json.loads((seq / "labels" / "000001.json").read_text())["defects"]
    recipe = yaml.safe_load((ROOT / "recipes" / "steel_plate.yaml").read_text())
    recipe["camera"]["settings"] = {"path": str(seq), "rate_fps": 0, "loop": False}
    recipe["stereo"]["working_distance_mm"] = [300, 700]
    recipe["detector"] = {"plugin": "fixed_roi", "confidence": 0.3,
                          "settings": {"regions": [{"name": d["class"], "box": d["box"]} for d in truth]}}
    recipe["outputs"] = [{"plugin": "log", "settings": {"file": str(tmp_path / "rejects.log")}}]
    recipe["results"] = {"path": str(tmp_path / "results")}
    recipe["verify"] = {"path": str(seq)}  # its own plate as the master part: the check's verdicts are not stored
    path = write_recipe(tmp_path / "r.yaml", yaml.safe_dump(recipe))
    ran = cli("run", str(path), env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert ran.returncode == 0, ran.stdout + ran.stderr
    assert f"master parts {seq}: 1 inspected" in ran.stdout
    evaluated = cli("eval", "depth", str(seq), "--set", "stereo.working_distance_mm=[300,700]", "--out",
                    str(tmp_path / "eval"), "--quiet", "--no-figure")
    assert evaluated.returncode == 0, evaluated.stderr
    rows = {tuple(r["box"]): r for r in json.loads((tmp_path / "eval" / "depth_eval.json").read_text())["rows"]}
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    stored = db.execute("SELECT x0, y0, x1, y1, distance_mm, deviation_mm, deviation_sigma_mm FROM defects").fetchall()
    assert len(stored) == len(truth) == len(rows)
    for *box, distance, deviation, sigma in stored:
        row = rows[tuple(box)]
        assert row["method"] == "surface" and deviation is not None
        assert (distance, deviation, sigma) == pytest.approx(
            (row["distance_mm"], row["deviation_mm"], row["deviation_sigma_mm"]), abs=1e-6)


def test_a_master_part_rejected_only_for_a_box_beside_its_defect_keeps_the_line_from_starting(tmp_path,
                                                                                                external_plugin_site):
    """A detector that puts a box somewhere else on a defective master part (the wrong model, say), a box some rule
    rejects, had the part counted as caught: its own defect, on a plate of its own, would have passed."""
    source = ROOT / "sim_fixtures" / "plates_textured"
    seq = tmp_path / "seq"
    for folder, name in (("left", "000001.jpg"), ("right", "000001.jpg"), ("labels", "000001.json")):
        (seq / folder).mkdir(parents=True)
        shutil.copy(source / folder / name, seq / folder / name)
    shutil.copy(source / "calib.yaml", seq / "calib.yaml")
    recipe = yaml.safe_load((ROOT / "recipes" / "steel_plate.yaml").read_text())
    recipe["camera"]["settings"] = {"path": str(seq), "rate_fps": 0, "loop": False}
    recipe["stereo"]["working_distance_mm"] = [300, 700]
    recipe["detector"] = {"plugin": "fixed_roi", "confidence": 0.3,
                          "settings": {"regions": [{"name": "decoy", "box": [440, 60, 490, 110]}]}}
    recipe["decision"]["rules"].append({"class": "decoy", "quantity": "confidence", "op": ">", "threshold": 0.5})
    recipe["outputs"] = [{"plugin": "log", "settings": {"file": str(tmp_path / "rejects.log")}}]
    recipe["results"] = {"path": str(tmp_path / "results")}
    recipe["verify"] = {"path": str(seq)}
    path = write_recipe(tmp_path / "r.yaml", yaml.safe_dump(recipe))
    ran = cli("run", str(path), env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert ran.returncode == 4, ran.stdout + ran.stderr
    # the 1.42 mm pit, not the 0.40 mm scratch or the 0.58 mm inclusion, which lie inside the limits
    assert (f"ALARM verify: 1 master part with a defect beyond a limit got through (passed, or rejected only for "
            f"another box) (frame 000001 of {seq}; 000001's pitted_surface at (208, 255)-(243, 330) rejected by no "
            f"box of its own): the line would pass such parts") in ran.stdout
    assert "parts 0  passed 0" in ran.stdout


def _broken_package(site):
    """A package whose entry point cannot be imported (a dependency missing), as pip would leave it."""
    info = site / "broken_plugin-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: broken-plugin\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[stereo_inspect]\nbroken = broken_plugin_module\n")
    (site / "broken_plugin_module.py").write_text("import a_dependency_nobody_installed\n")
    return site


def test_a_package_that_fails_to_load_leaves_the_others_and_is_named(tmp_path, plane_sequence):
    env = {"PYTHONPATH": str(_broken_package(tmp_path / "site"))}
    listed = cli("plugins", env_extra=env)
    assert listed.returncode == 0 and "replay" in listed.stdout, listed.stderr
    assert "failed to load: broken-plugin 1.0 (broken): ModuleNotFoundError" in listed.stderr
    info = plane_sequence([0.0])
    recipe = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"]))
    assert cli("validate", str(recipe), "--set", "detector.plugin=yolov8", "--set", "detector.settings={}",
               "--set", "decision.rules.0.class=any", env_extra=env).returncode == 0
    named = cli("validate", str(recipe), env_extra=env)  # a recipe naming a plugin that is not there says why
    assert named.returncode == 2 and "unknown detector plugin 'fixed_roi'" in named.stderr
    assert "these plugin packages failed to load: broken-plugin 1.0 (broken): ModuleNotFoundError" in named.stderr


def test_a_name_two_packages_register_is_refused_naming_both():
    class Impostor:
        @hookimpl
        def stereo_inspect_cameras(self):
            return [PluginSpec("replay", "camera", lambda settings, ctx: None)]

    registry = Registry(make_manager((Impostor(),)))
    with pytest.raises(PluginConflict, match=r"camera plugin 'replay' is registered by stereo-inspect [\d.]+ and by "
                                             r"registered in-process: uninstall one of them"):
        registry.get("camera", "replay")
    assert "replay" not in registry.names("camera") and "zed" in registry.names("camera")


def test_a_hook_that_fails_or_returns_something_else_is_left_out_and_named():
    class Failing:
        @hookimpl
        def stereo_inspect_detectors(self):
            raise RuntimeError("licence server unreachable")

    class Confused:
        @hookimpl
        def stereo_inspect_outputs(self):
            return [PluginSpec("plc", "camera", lambda settings, ctx: None), {"name": "plc"}]

    registry = Registry(make_manager((Failing(), Confused())))
    assert "yolov8" in registry.names("detector") and "modbus" in registry.names("output")
    failed = "\n".join(registry.failed)
    assert "RuntimeError: licence server unreachable" in failed
    assert "stereo_inspect_outputs returned 'plc', a camera" in failed and "stereo_inspect_outputs returned dict" in failed
    with pytest.raises(UnknownPlugin, match="these plugin packages failed to load: .*licence server unreachable"):
        registry.get("detector", "their_detector")
