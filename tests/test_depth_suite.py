"""``inspect eval depth-suite`` and the suite file it reads (``core/depth_suite.py``)."""
from __future__ import annotations

import json

import pytest
from conftest import cli, cli_here

from core import depth_suite as ds

TINY = ("generate --frames 2 --seed 5 --synthetic-defects --width 320 --height 200 --distance-range-mm 350 450 "
        "--defect-size-px 20 40 --depth-range-mm 0.3 2.5")


def write_suite(path, sets: dict[str, str], groups: str) -> None:
    path.write_text("sets:\n" + "".join(f"  {name}: {command}\n" for name, command in sets.items())
                    + "groups:\n" + groups)


class TestLoadSuite:
    def test_the_shipped_suite_holds_every_set_in_a_group_and_renders_each_with_a_renderer(self):
        suite = ds.load_suite()
        assert len(suite.sets) > 50 and "nine" in suite.groups
        assert {s for g in suite.groups.values() for s in g.sets} == set(suite.sets)  # no set left unscored
        assert all(words[0] in ds.RENDERERS for words in suite.sets.values())
        assert suite.groups["nine"].sets == tuple(s for s in suite.sets if s.startswith("eval/"))
        assert suite.groups["boxes_2x"].options[-2:] == ("--box-scale", "2.0")

    def test_render_args_put_the_set_in_its_folder_under_the_root(self, tmp_path):
        suite = ds.load_suite()
        assert suite.render_args("raycast/tex", tmp_path) == ["sim", "raycast", str(tmp_path / "raycast/tex"),
                                                              "--kind", "textured", "--seed", "1"]

    @pytest.mark.parametrize("sets, groups, said", [
        ({"a/x": TINY}, "  g:\n    sets: [a/y]\n", "groups.g.sets: 'a/y' is none of the file's sets; did you mean 'a/x'?"),
        ({"a/x": TINY}, "  g:\n    sets: [b/*]\n", "groups.g.sets: 'b/*' is none of the file's sets"),
        ({"a/x": "render --seed 1"}, "  g:\n    sets: [a/x]\n", "sets.a/x: expected an `inspect sim` command"),
        ({"../x": TINY}, "  g:\n    sets: [../x]\n", "sets.../x: a set's name is a folder under the suite's root"),
        ({"a/x": TINY + " --seed 'unclosed"}, "  g:\n    sets: [a/x]\n", "sets.a/x: No closing quotation"),
        ({"a/x": TINY}, "  g:\n    sets: [a/x]\n    options: 5\n", "groups.g.options: expected a command line"),
        ({"a/x": TINY}, "  g:\n    sets: [a/x]\n    option: --threads 1\n", "groups.g: expected {sets: [...], options"),
    ])
    def test_a_bad_suite_is_an_error_naming_the_file_and_the_key(self, tmp_path, sets, groups, said):
        path = tmp_path / "suite.yaml"
        write_suite(path, sets, groups)
        with pytest.raises(ds.SuiteError) as caught:
            ds.load_suite(path)
        assert str(caught.value).startswith(f"{path}: ") and said in str(caught.value), str(caught.value)

    def test_a_file_that_is_not_the_suite_s_two_mappings_is_an_error(self, tmp_path):
        path = tmp_path / "suite.yaml"
        path.write_text("sets: {}\n")
        with pytest.raises(ds.SuiteError, match="expected the two mappings"):
            ds.load_suite(path)
        path.write_text("sets: [a\n")
        with pytest.raises(ds.SuiteError, match=r"line \d+: not YAML"):
            ds.load_suite(path)
        # YAML keeps the second group of one name without a word: the first would never be scored
        path.write_text(f"sets:\n  a/x: {TINY}\ngroups:\n  g: {{sets: [a/x]}}\n  g: {{sets: [a/x]}}\n")
        with pytest.raises(ds.SuiteError, match=r"suite.yaml: line 5: groups.g: given twice \(first at line 4\)"):
            ds.load_suite(path)
        path.write_text(f"sets:\n  a/x: {TINY}\ngroups:\n  g: {{sets: [a/x], seeds: 010}}\n")
        with pytest.raises(ds.SuiteError, match=r"suite.yaml: line 4: groups.g.seeds: 010: YAML reads a leading zero"):
            ds.load_suite(path)
        with pytest.raises(ds.SuiteError, match="cannot be read"):
            ds.load_suite(tmp_path / "missing.yaml")

    def test_an_unknown_group_is_named_with_the_nearest(self):
        with pytest.raises(ds.SuiteError, match="no group 'nien'; did you mean 'nine'"):
            ds.load_suite().chosen(["nien"])
        assert [g.name for g in ds.load_suite().chosen(["raycast", "nine"])] == ["nine", "raycast"]  # the file's order


def row(sequence, frame, truth, proven, clear_cut=True, box=(0, 0, 10, 10)):
    return {"sequence": sequence, "frame_id": frame, "box": list(box), "true_status": truth, "proven": proven,
            "clear_cut": clear_cut}


class TestRowsTable:
    def test_the_errors_parts_are_shares_of_its_squares_or_not_available_without_a_truth(self):
        row = {"group": "g", "defects": 3, "measured": 3, "error_mm": {}, "error_over_floor": {}, "per_defect": None,
               "ratio": None, "within_2_sigma": None, "sigma_over_floor": None, "texture_per_defect": None,
               "texture_sigma": None, "distance_percent": None, "distance_within_2_sigma": None,
               "distance_per_defect": None, "silent_pass": 0, "proven_pass": 0, "undecided_pass": 0,
               "proven_reject": 0, "undecided_reject": 0}
        with_parts = ds.rows_table([{**row, "parts": {"ring": 0.094, "region": 0.896, "extent": 0.01}}])
        assert "| 9 / 90 / 1 % |" in with_parts and "ring / region's estimate / region's extent" in with_parts
        assert "| n/a |" in ds.rows_table([{**row, "parts": {}}])
        exact = {"ring": None, "region": None, "extent": None}  # every part zero: no shares to give
        assert "| n/a |" in ds.rows_table([{**row, "parts": exact}])


class TestUndecidedTable:
    def test_the_parts_most_often_largest_first_with_their_counts_inside_and_beyond(self):
        tally = {"noise": {"PASS": 1}, "moved": {"PASS": 2, "REJECT": 3}, "surface": {"REJECT": 2},
                 "wall": {"PASS": 1}, "band": {"REJECT": 1}}
        table = ds.undecided_table([{"group": "g", "undecided_pass": 4, "undecided_reject": 6, "undecided_from": tally},
                                    {"group": "none undecided", "undecided_from": {}}])
        row = [line for line in table.splitlines() if line.startswith("| g |")]
        assert row == ["| g | 4 / 6 | the region moved within its box 2 / 3; placing the surface around the box 0 / 2; "
                       "the sensor's noise over the region's texture 1 / 0; 2 more |"]
        assert "none undecided" not in table

    def test_nothing_where_no_group_left_any_undecided(self):
        assert ds.undecided_table([{"group": "g", "undecided_from": {}}]) == ""


class TestDecisionChanges:
    def test_counts_each_side_lost_and_gained_and_the_silent_passes(self):
        before = [row("s", "0", "PASS", "PASS"), row("s", "1", "PASS", "undecided"),
                  row("s", "2", "REJECT", "REJECT"), row("s", "3", "REJECT", "undecided"), row("s", "4", "REJECT", "PASS")]
        after = [row("s", "0", "PASS", "undecided"), row("s", "1", "PASS", "PASS"),
                 row("s", "2", "REJECT", "REJECT"), row("s", "3", "REJECT", "PASS"), row("s", "4", "REJECT", "undecided")]
        # the same defects in another order compare alike
        assert ds.decision_changes(before, after[::-1]) == {
            "good_lost": 1, "good_gained": 1, "beyond_lost": 0, "beyond_gained": 0, "wrong_before": 1,
            "wrong_after": 1, "silent_before": 1, "silent_after": 1}

    def test_a_part_beyond_the_limit_no_longer_proven_and_one_not_clear_cut_is_no_silent_pass(self):
        before = [row("s", "0", "REJECT", "REJECT"), row("s", "1", "REJECT", "PASS", clear_cut=False)]
        after = [row("s", "0", "REJECT", "undecided"), row("s", "1", "REJECT", "PASS", clear_cut=False)]
        c = ds.decision_changes(before, after)
        assert c["beyond_lost"] == 1 and c["silent_before"] == c["silent_after"] == 0
        assert c["wrong_before"] == c["wrong_after"] == 1

    def test_every_defect_proven_on_the_wrong_side_counts_however_near_its_limit(self):
        # a change that narrows sigma may prove defects near the limit on the wrong side, none of them clear-cut
        before = [row("s", "0", "REJECT", "undecided", clear_cut=False), row("s", "1", "PASS", "undecided"),
                  row("s", "2", "PASS", "PASS")]
        after = [row("s", "0", "REJECT", "PASS", clear_cut=False), row("s", "1", "PASS", "REJECT"),
                 row("s", "2", "PASS", "PASS")]
        c = ds.decision_changes(before, after)
        assert (c["wrong_before"], c["wrong_after"]) == (0, 2)
        assert c["silent_after"] == 0 and c["good_lost"] == c["beyond_gained"] == 0
        assert "| g | 0 | 0 | 0 | 0 | 0 → 2 | 0 → 0 |" in ds.changes_table({"g": c})

    def test_other_defects_cannot_be_compared(self):
        with pytest.raises(ValueError, match="not measure the same defects"):
            ds.decision_changes([row("s", "0", "PASS", "PASS")], [row("t", "0", "PASS", "PASS")])


def test_renders_the_missing_sets_scores_each_group_and_compares_with_an_earlier_run(tmp_path):
    suite = tmp_path / "suite.yaml"
    write_suite(suite, {"plates/tiny": TINY},
                "  true_boxes:\n    sets: [plates/*]\n"
                "  larger:\n    sets: [plates/tiny]\n    options: --box-scale 1.3\n")
    root, out = tmp_path / "runs", tmp_path / "first"
    result = cli("eval", "depth-suite", str(root), "--suite", str(suite), "--out", str(out), "--threads", "1")
    assert result.returncode == 0, result.stderr
    assert "rendering plates/tiny" in result.stdout and ds.is_rendered(root / "plates" / "tiny")
    body = json.loads((out / "suite.json").read_text())
    assert [r["group"] for r in body["rows"]] == ["true_boxes", "larger"]
    for r in body["rows"]:  # each row is its group's own report
        report = json.loads((out / r["group"] / "depth_eval.json").read_text())["all"]["measurement"]
        assert r["defects"] == report["defects"] > 0 and r["per_defect"] == report["error_over_floor_per_defect"]
        # the rendered sets hold their true disparity: the error's parts, shares of its squares
        assert r["parts"] == {name: report["error_parts"][name]["share"] for name in ("ring", "region", "extent")}
        assert sum(r["parts"].values()) == pytest.approx(1.0)
    assert json.loads((out / "larger" / "depth_eval.json").read_text())["box_scale"] == 1.3
    assert "| true_boxes |" in (out / "suite.md").read_text() and "--box-scale 1.3" in (out / "suite.md").read_text()
    # what the undecided defects' uncertainty was made of, where a group left any undecided
    undecided = sum(r["undecided_pass"] + r["undecided_reject"] for r in body["rows"])
    assert ("What the undecided defects' uncertainty" in (out / "suite.md").read_text()) == (undecided > 0)
    assert all(sum(sum(by.values()) for by in r["undecided_from"].values())
               == r["undecided_pass"] + r["undecided_reject"] for r in body["rows"])
    # a second run renders nothing, and decides every defect as the first did
    again = cli("eval", "depth-suite", str(root), "--suite", str(suite), "--out", str(tmp_path / "second"),
                "--threads", "1", "--group", "true_boxes", "--against", str(out))
    assert again.returncode == 0, again.stderr
    assert "rendering" not in again.stdout
    changes = json.loads((tmp_path / "second" / "suite.json").read_text())["changes"]
    assert changes == {"true_boxes": dict.fromkeys(("good_lost", "good_gained", "beyond_lost", "beyond_gained",
                                                    "wrong_before", "wrong_after", "silent_before", "silent_after"), 0)}


def test_a_set_that_cannot_be_rendered_is_a_one_line_error_naming_it(tmp_path):
    suite = tmp_path / "suite.yaml"
    write_suite(suite, {"plates/bad": "generate --frames 1 --width 10"}, "  g:\n    sets: [plates/bad]\n")
    result = cli_here("eval", "depth-suite", str(tmp_path / "runs"), "--suite", str(suite), "--out", str(tmp_path / "o"))
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: set plates/bad"), result.stderr
    assert "--width" in lines[0]
