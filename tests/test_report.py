from __future__ import annotations

import csv
import json
import re
import shutil
from dataclasses import replace
from pathlib import Path

import pytest
import stereo_inspect_fixed_roi
from conftest import cli_here, write_recipe
from test_engine import RECIPE

from core import engine
from core.recipe import load_recipe
from core.registry import Registry, make_manager
from core.types import DefectMeasurement, Detection, PartResult, Status, UncertaintyPart, Verdict


@pytest.fixture
def results(tmp_path, plane_sequence):
    info = plane_sequence([0.0, 6.0, 0.0])
    (info["folder"] / "right" / "000002.png").unlink()
    registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log")), registry=registry)
    engine.run(loaded, registry=registry, device="cpu")
    return tmp_path / "results"


def test_report_counts_and_yield(results):
    out = cli_here("report", str(results))
    assert out.returncode == 0, out.stderr
    assert "parts 3  passed 1  rejected 1  errors 1  yield 33.3%" in out.stdout
    assert "pit" in out.stdout and "PASS 1" in out.stdout and "REJECT 1" in out.stdout


@pytest.mark.parametrize("name", ["results.db", "results.db-wal"])
def test_a_csv_over_the_store_is_refused(results, name):
    # `--csv results/results.db`, a completed file name: the CSV replaced the whole inspection record
    before = (results / "results.db").read_bytes()
    out = cli_here("report", str(results), "--csv", str(results / name))
    assert out.returncode == 2 and out.stderr == (f"error: --csv {results / name}: the command reads that file: "
                                                  f"writing it would destroy it\n"), out.stderr
    assert (results / "results.db").read_bytes() == before


def test_report_csv_export(results, tmp_path):
    target = tmp_path / "parts.csv"
    out = cli_here("report", str(results / "results.db"), "--csv", str(target))
    assert out.returncode == 0
    rows = list(csv.DictReader(target.open()))
    assert [r["part_verdict"] for r in rows] == ["PASS", "REJECT", "ERROR"]
    assert rows[2]["class"] == "" and "right image of frame 000002 missing" in rows[2]["error"]
    assert float(rows[1]["deviation_mm"]) > 1.5


def test_report_on_missing_store(tmp_path):
    out = cli_here("report", str(tmp_path / "nothing"))
    assert out.returncode == 2 and out.stderr.startswith("error: ") and "no results store" in out.stderr


@pytest.mark.parametrize("run", ["2", "0", "-1", "99999999999999999999"])  # the last overflowed SQLite's integer
def test_a_run_the_store_does_not_hold_is_an_error_not_a_run_without_parts(results, run):
    out = cli_here("report", str(results), "--run", run)
    assert out.returncode == 2 and out.stdout == ""
    assert out.stderr == f"error: {results / 'results.db'}: no run {run} (runs 1-1)\n"


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full (a device that is always full) here")
def test_a_csv_the_disk_cannot_hold_is_named(results):
    out = cli_here("report", str(results), "--csv", "/dev/full")
    assert out.returncode == 2, out.stderr
    assert out.stderr == "error: /dev/full: could not be written (No space left on device)\n", out.stderr


def test_report_csv_of_one_run(results, tmp_path):
    from core.recipe import load_recipe as load
    from core.registry import Registry, make_manager

    registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
    engine.run(load(tmp_path / "r.yaml", registry=registry), registry=registry, device="cpu")  # run 2, same plates
    target = tmp_path / "run2.csv"
    out = cli_here("report", str(results), "--run", "2", "--csv", str(target))
    assert out.returncode == 0, out.stderr
    rows = list(csv.DictReader(target.open()))
    assert len(rows) == 3 and {r["run_id"] for r in rows} == {"2"}


def test_a_store_of_an_older_version_is_read_and_migrated(tmp_path):
    import sqlite3

    from core import store

    old_schema = store.SCHEMA.replace("    flagged INTEGER DEFAULT 0,\n", "").replace(
        ",\n    distance_sigma_mm REAL,\n    deviation_sigma_mm REAL,\n    depth_method TEXT,\n    uncertainty TEXT", "")
    db = sqlite3.connect(tmp_path / "results.db")
    db.executescript(old_schema)
    db.execute("INSERT INTO runs (recipe_name, recipe_hash, recipe_path, started) VALUES ('old', 'h', 'p', 0)")
    db.execute("INSERT INTO parts (run_id, part_id, frame_id, frame_index, time, verdict, reasons) "
               "VALUES (1, 'R1-000000', '000000', 0, 0, 'REJECT', '[]')")
    db.execute("INSERT INTO defects (part_row, class, confidence, distance_mm, deviation_mm, verdict, reasons) "
               "VALUES (1, 'pit', 0.9, 400, 1.5, 'REJECT', '[]')")
    db.commit()
    db.close()
    readonly = store.open_readonly(tmp_path)
    rows = store.csv_rows(readonly, 1)  # read as it is: the new columns come back empty
    assert rows[0][-4:] == (None, None, None, None) and len(rows[0]) == len(store.CSV_COLUMNS)
    assert store.undecided_by_cause(readonly) == {}  # no account kept then: nothing to tally
    readonly.close()
    writer = store.ResultsStore(tmp_path)  # opened for writing, it gains them
    columns = {row[1] for row in writer.db.execute("PRAGMA table_info(defects)")}
    assert {"distance_sigma_mm", "deviation_sigma_mm", "depth_method", "uncertainty"} <= columns
    writer.close()


def _undecided(kind: str, cause: str) -> tuple[DefectMeasurement, tuple[Status, list[str]]]:
    m = DefectMeasurement(Detection("pit", 0.9, (0, 0, 10, 10)), 400.0, 0.9, 1.0, 0.1, 10.0,
                          deviation_sigma_mm=0.2, method="surface",
                          uncertainty_parts=(UncertaintyPart("surface", "placing the surface around the box", 0.01),
                                             UncertaintyPart(kind, cause, 0.03)))
    return m, (Status.REJECT, ["pit (0.90): deviation_mm 0.90 ± 0.40 straddles 1, conformance not proven (rule 'r', "
                               f"uncertain: reject); its uncertainty: 75 % from {cause}"])


def test_the_store_keeps_each_defect_s_uncertainty_and_report_tallies_the_undecided_by_it(tmp_path):
    from core import store

    writer = store.ResultsStore(tmp_path)
    run = writer.start_run("r", "h", "r.yaml", None, {}, ["log"])
    moved = _undecided("moved", "the region moved 12 px down, which reads 1.60 mm: the box may not hold its defect")
    noise = _undecided("noise", "the sensor's noise over the region's texture")
    proven = (replace(noise[0], deviation_mm=2.0), (Status.REJECT, ["pit (0.90): deviation_mm 2.00 ± 0.40 > 1"]))
    matcher = (replace(noise[0], uncertainty_parts=(), method="disparity"), noise[1])
    distance = (moved[0], (Status.REJECT, ["pit (0.90): distance_mm 400.00 ± 0.40 straddles 400.1, conformance not "
                                           "proven (rule 'r', uncertain: reject)"]))
    for i, defects in enumerate([[moved], [moved, noise], [proven], [matcher], [distance]]):
        part = PartResult(f"P{i}", f"{i:06d}", i, float(i), Verdict(Status.REJECT), [m for m, _ in defects])
        writer.record_part(run, part, [v for _, v in defects])
    writer.close()
    db = store.open_readonly(tmp_path)
    assert store.undecided_by_cause(db) == {"moved": 2, "noise": 1, "": 1}
    kept = json.loads(db.execute("SELECT uncertainty FROM defects ORDER BY id").fetchone()[0])
    assert kept == [{"kind": "surface", "cause": "placing the surface around the box", "variance_mm2": 0.01},
                    {"kind": "moved", "cause": moved[0].uncertainty_parts[1].cause, "variance_mm2": 0.03}]
    db.close()
    out = cli_here("report", str(tmp_path))
    assert out.returncode == 0, out.stderr
    tally = out.stdout.split("by the largest part of their uncertainty:\n")[1].splitlines()
    assert [line.split(None, 1) for line in tally[:3]] == [
        ["2", "the region moved within its box"], ["1", "the sensor's noise over the region's texture"],
        ["1", "no account of it (the matcher's map alone)"]]
    out = cli_here("report", str(tmp_path), "--csv", str(tmp_path / "d.csv"))
    with open(tmp_path / "d.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert json.loads(rows[0]["uncertainty"])[1]["kind"] == "moved" and rows[4]["uncertainty"] == ""  # the matcher's


class TestUncertaintyAccount:
    def test_the_column_as_the_store_wrote_it(self):
        from core import store

        text = '[{"kind": "noise", "cause": "the sensor\'s noise", "variance_mm2": 0.01}]'
        assert store.uncertainty_account(text) == [{"kind": "noise", "cause": "the sensor's noise", "variance_mm2": 0.01}]

    @pytest.mark.parametrize("text", [None, "", "not json", "{}", "[1, 2]", '[{"kind": "noise"}]',
                                      '[{"kind": "noise", "cause": "c", "variance_mm2": "big"}]',
                                      '[{"kind": "noise", "cause": "c", "variance_mm2": NaN}]'])
    def test_anything_else_is_no_account(self, text):
        from core import store

        assert store.uncertainty_account(text) == []

    def test_an_account_with_a_part_that_is_not_a_number_is_not_written(self):
        from core import store

        m = DefectMeasurement(Detection("pit", 0.9, (0, 0, 10, 10)), 400.0, 0.9, 1.0, 0.1, 10.0,
                              uncertainty_parts=(UncertaintyPart("noise", "n", float("nan")),))
        assert store.uncertainty_json(m) is None
        assert json.loads(store.uncertainty_json(replace(m, uncertainty_parts=(UncertaintyPart("noise", "n", 0.5),)))) \
            == [{"kind": "noise", "cause": "n", "variance_mm2": 0.5}]


def test_report_names_no_undecided_where_every_rule_decided(results):
    assert "could decide" not in cli_here("report", str(results)).stdout


class TestAFileThatIsNotAStore:
    """A results.path at a damaged file or another program's database: one line naming it, before a run
    starts, and the file left as it was."""

    @pytest.fixture(params=["garbage", "foreign", "empty"])
    def not_a_store(self, request, tmp_path):
        import sqlite3

        path = tmp_path / "store" / "results.db"
        path.parent.mkdir()
        if request.param == "garbage":
            path.write_bytes(b"not a database at all, just bytes " * 40)
        elif request.param == "foreign":
            db = sqlite3.connect(path)
            db.execute("CREATE TABLE parts (sku TEXT, price REAL)")
            db.commit()
            db.close()
        else:
            path.write_bytes(b"")
        return path

    @pytest.mark.parametrize("command", ["report", "view"])
    def test_report_and_view_name_it(self, not_a_store, command):
        out = cli_here(command, str(not_a_store.parent))
        assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
        assert out.stderr.startswith(f"error: {not_a_store}: not a results store that can be used (")

    @pytest.mark.parametrize("command", ["report", "view"])
    @pytest.mark.parametrize("table", ["defects", "alarms"])
    def test_a_store_without_a_table_they_read_is_named_by_report_and_view(self, results, tmp_path, command, table):
        # a run opening it for writing makes the table again; reading, it would end in a traceback
        import sqlite3

        path = tmp_path / "results.db"
        shutil.copy(results / "results.db", path)
        db = sqlite3.connect(path)
        db.execute(f"DROP TABLE {table}")
        db.commit()
        db.close()
        out = cli_here(command, str(path))
        assert out.returncode == 2 and out.stderr == (f"error: {path}: not a results store that can be used (no table "
                                                      f"{table}): move it aside or give another results.path\n")

    def test_a_store_whose_pages_do_not_read_is_named_by_report_and_run(self, results, tmp_path, plane_sequence):
        # its schema on the first page reads, so it passed as a store; the first query past it ended in a
        # traceback (report), or in one before the run's first part (inspect run)
        import sqlite3

        path = tmp_path / "damaged" / "results.db"
        path.parent.mkdir()
        shutil.copy(results / "results.db", path)
        page = sqlite3.connect(path).execute("PRAGMA page_size").fetchone()[0]
        data = path.read_bytes()
        path.write_bytes(data[:page] + b"\xff" * (len(data) - page))  # every page but the schema's
        before = path.read_bytes()
        says = (f"{path}: the results store is damaged (database disk image is malformed): move it aside "
                f"(sqlite3's .recover can save what it holds) or give another results.path\n")
        out = cli_here("report", str(path.parent))
        assert out.returncode == 2 and out.stderr == f"error: {says}", out.stderr
        registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
        info = plane_sequence([0.0])
        text = RECIPE.format(box=info["box"], output="log").replace("path: results", f"path: {path.parent}")
        with pytest.raises(engine.SetupError, match=re.escape(says.strip())):
            engine.run(load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry), registry=registry,
                       device="cpu")
        assert path.read_bytes() == before  # left as it was, for the recovery

    def test_validate_names_it_and_leaves_it_as_it_was(self, not_a_store, tmp_path, plane_sequence):
        from core.store import store_problem

        info = plane_sequence([0.0])
        before = not_a_store.read_bytes()
        registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
        text = RECIPE.format(box=info["box"], output="log")
        loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text.replace("path: results",
                                                                          f"path: {not_a_store.parent}")), registry=registry)
        problem = store_problem(loaded.resolve(loaded.recipe.results.path))
        if not before:  # an empty file is SQLite's empty database: a new store
            assert problem is None
        else:
            assert problem.startswith(f"{not_a_store}: not a results store that can be used (")
        assert not_a_store.read_bytes() == before
        blocked = load_recipe(write_recipe(tmp_path / "b.yaml", text.replace("path: results", f"path: {not_a_store}/x")),
                              registry=registry)
        assert store_problem(blocked.resolve(blocked.recipe.results.path)) == f"{not_a_store}/x: cannot be created ({not_a_store} is a file, not a folder)"

    def test_a_run_refuses_it_before_it_starts_and_leaves_it_as_it_was(self, not_a_store, tmp_path, plane_sequence):
        info = plane_sequence([0.0])
        before = not_a_store.read_bytes()
        recipe = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log").replace(
            "path: results", f"path: {not_a_store.parent}"))
        registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
        if not before:  # an empty file is SQLite's empty database: a new store
            assert engine.run(load_recipe(recipe, registry=registry), registry=registry, device="cpu").frames == 1
            return
        with pytest.raises(engine.SetupError, match=r"results\.path: .*results\.db: not a results store that can be used"):
            engine.run(load_recipe(recipe, registry=registry), registry=registry, device="cpu")
        assert not_a_store.read_bytes() == before
