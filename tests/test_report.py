from __future__ import annotations

import csv

import pytest
import stereo_inspect_fixed_roi
from conftest import cli, write_recipe
from test_engine import RECIPE

from core import engine
from core.recipe import load_recipe
from core.registry import Registry, make_manager


@pytest.fixture
def results(tmp_path, plane_sequence):
    info = plane_sequence([0.0, 6.0, 0.0])
    (info["folder"] / "right" / "000002.png").unlink()
    registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log")), registry=registry)
    engine.run(loaded, registry=registry, device="cpu")
    return tmp_path / "results"


def test_report_counts_and_yield(results):
    out = cli("report", str(results))
    assert out.returncode == 0, out.stderr
    assert "parts 3  passed 1  rejected 1  errors 1  yield 33.3%" in out.stdout
    assert "pit" in out.stdout and "PASS 1" in out.stdout and "REJECT 1" in out.stdout


def test_report_csv_export(results, tmp_path):
    target = tmp_path / "parts.csv"
    out = cli("report", str(results / "results.db"), "--csv", str(target))
    assert out.returncode == 0
    rows = list(csv.DictReader(target.open()))
    assert [r["part_verdict"] for r in rows] == ["PASS", "REJECT", "ERROR"]
    assert rows[2]["class"] == "" and "right image of frame 000002 missing" in rows[2]["error"]
    assert float(rows[1]["deviation_mm"]) > 1.5


def test_report_on_missing_store(tmp_path):
    out = cli("report", str(tmp_path / "nothing"))
    assert out.returncode == 2 and out.stderr.startswith("error: ") and "no results store" in out.stderr


def test_report_csv_of_one_run(results, tmp_path):
    from core.recipe import load_recipe as load
    from core.registry import Registry, make_manager

    registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
    engine.run(load(tmp_path / "r.yaml", registry=registry), registry=registry, device="cpu")  # run 2, same plates
    target = tmp_path / "run2.csv"
    out = cli("report", str(results), "--run", "2", "--csv", str(target))
    assert out.returncode == 0, out.stderr
    rows = list(csv.DictReader(target.open()))
    assert len(rows) == 3 and {r["run_id"] for r in rows} == {"2"}
