"""Master parts (``verify.path``): known parts inspected before the line's first plate; a defective one that
passes keeps the run from reading any plate."""
from __future__ import annotations

import json
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import cv2
import pytest
from conftest import ROOT, cli, cli_here

from core.recipe.schema import DecisionSection
from core.types import Status, Verdict
from core.verification import (MasterPart, Verification, beyond_a_limit, boxes_off, known_verdict, known_verdicts,
                               missed_defects, only_undecided, verify)

DEMO = ROOT / "recipes" / "steel_plate.yaml"
FIXTURE = ROOT / "sim_fixtures" / "steel_plate"
MASTERS = ROOT / "sim_fixtures" / "steel_plate_masters"  # the demo recipe's: four of its plates
BOTH_WAYS = DecisionSection(rules=[
    {"class": "any", "quantity": "deviation_mm", "op": ">", "threshold": 1.0},
    {"class": "any", "quantity": "deviation_mm", "op": "<", "threshold": -1.0},
])


def _labels(*defects: tuple[str, float | None]) -> dict:
    return {"defects": [{"class": cls, "box": [0, 0, 10, 10], "deviation_mm": deviation} for cls, deviation in defects]}


class TestKnownVerdict:
    @pytest.mark.parametrize("deviation, expected", [
        (1.3, Status.REJECT), (2.5, Status.REJECT), (-1.3, Status.REJECT),  # clearly beyond either limit
        (1.1, None), (0.8, None), (-0.75, None),  # within 0.3 mm of one: a measurement may prove neither side
        (0.69, Status.PASS), (0.0, Status.PASS), (-0.5, Status.PASS),
    ])
    def test_a_defects_depth_against_the_limits(self, deviation, expected):
        assert known_verdict(_labels(("pit", deviation)), BOTH_WAYS) is expected

    def test_a_part_without_defects_is_good(self):
        assert known_verdict({"defects": []}, BOTH_WAYS) is Status.PASS

    def test_one_clearly_defective_defect_makes_the_part_defective_whatever_the_others(self):
        assert known_verdict(_labels(("pit", 0.2), ("pit", 1.05), ("pit", 1.6)), BOTH_WAYS) is Status.REJECT

    def test_a_defect_near_a_limit_leaves_an_otherwise_good_part_unknown(self):
        assert known_verdict(_labels(("pit", 0.2), ("pit", 0.9)), BOTH_WAYS) is None

    def test_a_truth_without_the_ruled_quantity_decides_nothing(self):
        assert known_verdict(_labels(("pit", None)), BOTH_WAYS) is None

    def test_rules_of_other_classes_do_not_apply(self):
        decision = DecisionSection(rules=[{"class": "scratches", "quantity": "deviation_mm", "op": ">",
                                           "threshold": 1.0}])
        assert known_verdict(_labels(("pit", 3.0)), decision) is Status.PASS
        assert known_verdict(_labels(("scratches", 3.0)), decision) is Status.REJECT

    def test_a_rule_on_another_quantity_leaves_its_defect_undecided_by_the_labels(self):
        decision = DecisionSection(rules=[
            {"class": "scratches", "quantity": "deviation_mm", "op": ">", "threshold": 1.0},
            {"class": "pit", "quantity": "confidence", "op": ">", "threshold": 0.5},
        ], reject_unruled_defects=True)
        assert known_verdict(_labels(("pit", 0.1)), decision) is None  # ruled, on its confidence: not unruled
        assert known_verdict(_labels(("pit", 0.1), ("scratches", 3.0)), decision) is Status.REJECT

    def test_an_unruled_class_is_defective_where_the_recipe_rejects_unruled_defects(self):
        decision = DecisionSection(rules=[{"class": "scratches", "quantity": "deviation_mm", "op": ">",
                                           "threshold": 1.0}], reject_unruled_defects=True)
        assert known_verdict(_labels(("pit", 0.0)), decision) is Status.REJECT

    def test_an_inclusive_operator_counts_the_same_margin(self):
        decision = DecisionSection(rules=[{"class": "any", "quantity": "deviation_mm", "op": ">=", "threshold": 1.0}])
        assert known_verdict(_labels(("pit", 1.3)), decision) is Status.REJECT
        assert known_verdict(_labels(("pit", 1.29)), decision) is None


class TestVerification:
    def test_only_a_known_defective_part_that_passed_fails_the_check(self):
        fine = Verification("m", (MasterPart("1", Status.REJECT, Status.REJECT), MasterPart("2", Status.REJECT, Status.FLAG),
                                  MasterPart("3", Status.REJECT, Status.ERROR), MasterPart("4", Status.PASS, Status.REJECT),
                                  MasterPart("5", None, Status.PASS)))
        assert not fine.failed
        assert fine.summary() == ("master parts m: 5 inspected, 3 of 3 defective ones rejected, 0 of 1 good ones "
                                  "passed, 1 could not be inspected (ERROR), 1 near a limit (not counted)")
        failing = Verification("m", fine.parts + (MasterPart("6", Status.REJECT, Status.PASS),))
        assert failing.failed
        assert failing.refusal().startswith("1 master part with a defect beyond a limit passed (frame 6 of m)")

    def test_defective_master_parts_none_of_which_was_measured_fail_the_check(self):
        """A blind detector's parts are ERROR where their plate lies outside the working distance: errors
        alone show nothing of the detector."""
        errors = Verification("m", (MasterPart("1", Status.REJECT, Status.ERROR, "frame 1: no defect found, but ..."),
                                    MasterPart("2", Status.REJECT, Status.ERROR, "no defect found"),
                                    MasterPart("3", Status.PASS, Status.PASS)))
        assert errors.failed
        assert errors.refusal() == ("none of the 2 defective master parts of m could be inspected (frame 1: no defect "
                                    "found, but ...): nothing shows that the line finds a defect; the run does not "
                                    "start")
        one_measured = Verification("m", errors.parts + (MasterPart("4", Status.REJECT, Status.FLAG),))
        assert not one_measured.failed
        assert not Verification("m", (MasterPart("3", Status.PASS, Status.ERROR),)).failed  # nothing to show

    def test_the_refusal_names_the_first_five_frames(self):
        parts = tuple(MasterPart(f"{i:06d}", Status.REJECT, Status.PASS) for i in range(7))
        said = Verification("m", parts).refusal()
        assert said.startswith("7 master parts") and "000004 and 2 more of m" in said and "000005" not in said


class TestVerify:
    def test_the_demo_plates_hold_defective_and_good_parts(self):
        known = known_verdicts(FIXTURE, BOTH_WAYS)
        assert len(known) == 10 and Status.REJECT in known.values() and Status.PASS in known.values()

    def test_each_frame_is_held_against_its_labels(self):
        known = known_verdicts(FIXTURE, BOTH_WAYS)
        frames = [type("Frame", (), {"frame_id": frame_id})() for frame_id in sorted(known)]
        blind = verify(FIXTURE, frames, lambda item: (Verdict(Status.PASS), []), BOTH_WAYS)
        assert blind.failed
        assert {p.frame_id for p in blind.parts if p.passed_defective} == {
            f for f, status in known.items() if status is Status.REJECT}

        def own_boxes(item):  # each labelled defect rejected by a box of its own
            labels = json.loads((FIXTURE / "labels" / f"{item.frame_id}.json").read_text())
            return Verdict(Status.REJECT), [(tuple(d["box"]), Status.REJECT) for d in labels["defects"]]

        assert not verify(FIXTURE, frames, own_boxes, BOTH_WAYS).failed

    def test_a_part_rejected_for_another_box_than_its_defects_fails_the_check(self):
        """A box the wrong model put anywhere, read undecided, rejects the part: that says nothing of whether the
        line finds the defect, which on a plate of its own would pass."""
        known = known_verdicts(FIXTURE, BOTH_WAYS)
        frames = [type("Frame", (), {"frame_id": frame_id})() for frame_id in sorted(known)]
        elsewhere = verify(FIXTURE, frames, lambda item: (Verdict(Status.REJECT), [((0.0, 0.0, 20.0, 20.0),
                                                                                    Status.FLAG)]), BOTH_WAYS)
        assert elsewhere.failed
        missed = {p.frame_id: p.missed for p in elsewhere.parts if p.passed_defective}
        assert sorted(missed) == ["000002", "000003", "000006", "000008", "000009"]
        assert missed["000003"] == ("crazing at (250, 90)-(403, 160)",)  # not its 0.32 mm pit, inside the limits
        assert elsewhere.refusal().startswith(
            f"5 master parts with a defect beyond a limit got through (passed, or rejected only for another box) "
            f"(frames 000002, 000003, 000006, 000008, 000009 of {FIXTURE}; 000002's scratches at (335, 52)-(460, 75), "
            f"000003's crazing at (250, 90)-(403, 160), ")
        assert " and more rejected by no box of their own): the line would pass such parts" in elsewhere.refusal()

    def test_a_part_that_could_not_be_inspected_is_no_missed_defect(self):
        frames = [type("Frame", (), {"frame_id": "000003"})()]
        failed = verify(FIXTURE, frames, lambda item: (Verdict(Status.ERROR, ["frame 000003: no image"]), []),
                        BOTH_WAYS)
        (part,) = failed.parts
        assert part.missed == () and not part.passed_defective
        assert failed.failed and failed.refusal().startswith("none of the 1 defective master parts")


class TestOnlyUndecided:
    NOT_PROVEN = ("pit (0.90): deviation_mm 1.05 ± 0.40 straddles 1, conformance not proven (rule 'r', uncertain: "
                  "reject); its uncertainty: 75 % from the sensor's noise over the region's texture")

    def test_a_part_rejected_only_by_rules_that_could_not_decide(self):
        assert only_undecided(Verdict(Status.REJECT, [self.NOT_PROVEN, self.NOT_PROVEN])) == self.NOT_PROVEN
        assert only_undecided(Verdict(Status.FLAG, [self.NOT_PROVEN])) == self.NOT_PROVEN

    def test_a_proven_reject_among_them_or_another_outcome_is_not(self):
        proven = "pit (0.90): deviation_mm 2.05 ± 0.40 > 1 (rule 'r')"
        assert only_undecided(Verdict(Status.REJECT, [self.NOT_PROVEN, proven])) == ""
        assert only_undecided(Verdict(Status.PASS, [self.NOT_PROVEN])) == ""  # uncertain: pass
        assert only_undecided(Verdict(Status.ERROR, ["frame 000001: no image"])) == ""
        assert only_undecided(Verdict(Status.REJECT, [])) == ""

    def test_the_tally_says_which_defective_parts_were_caught_only_undecided_and_the_check_passes(self):
        parts = (MasterPart("1", Status.REJECT, Status.REJECT, undecided=self.NOT_PROVEN),
                 MasterPart("2", Status.REJECT, Status.REJECT), MasterPart("3", Status.PASS, Status.PASS))
        checked = Verification("m", parts)
        assert not checked.failed
        assert checked.summary() == (
            "master parts m: 3 inspected, 2 of 2 defective ones rejected, 1 of 1 good ones passed; 1 of them only as "
            f"undecided, not proven beyond the limit (frame 1: {self.NOT_PROVEN})")
        assert "undecided" not in Verification("m", parts[1:]).summary()

    def test_verify_keeps_the_reason_of_a_part_caught_only_undecided(self):
        frames = [type("Frame", (), {"frame_id": "000003"})()]
        labels = json.loads((FIXTURE / "labels" / "000003.json").read_text())
        boxes = [(tuple(d["box"]), Status.REJECT) for d in labels["defects"]]
        (part,) = verify(FIXTURE, frames, lambda item: (Verdict(Status.REJECT, [self.NOT_PROVEN]), boxes),
                         BOTH_WAYS).parts
        assert part.undecided == self.NOT_PROVEN and not part.passed_defective


class TestBoxesOff:
    DEFECTS = [{"class": "pit", "box": [100, 100, 140, 120]}, {"class": "crazing", "box": [300, 100, 330, 160]}]

    def test_a_box_more_than_a_third_off_its_defect_is_named(self):
        # the pit's box 16 px along its 40 px width (0.4), the crazing's 18 px down its 60 px height (0.3)
        assert boxes_off(self.DEFECTS, [(116, 100, 156, 120), (300, 118, 330, 178)]) == ["pit (0.40 of its size off)"]

    def test_boxes_on_their_defects_or_on_none_name_nothing(self):
        assert boxes_off(self.DEFECTS, [(101, 100, 141, 121), (300, 100, 330, 160)]) == []
        assert boxes_off(self.DEFECTS, [(0, 0, 20, 20)]) == []  # no box of theirs: missed_defects' to say
        assert boxes_off(self.DEFECTS, []) == [] and boxes_off([], [(0, 0, 20, 20)]) == []

    def test_the_tally_warns_of_them_and_the_check_still_passes(self):
        parts = (MasterPart("1", Status.REJECT, Status.REJECT, off=("pit (0.40 of its size off)",)),
                 MasterPart("2", Status.PASS, Status.PASS))
        checked = Verification("m", parts)
        assert not checked.failed
        assert checked.summary() == (
            "master parts m: 2 inspected, 1 of 1 defective ones rejected, 1 of 1 good ones passed; warning: the "
            "detector's box on 1's pit (0.40 of its size off) lies more than a third off its defect, where depth may "
            "prove a defect beyond its limit inside it (docs/depth-conditions.md, boxes that are off): check the "
            "detector with inspect eval detector-frames")
        two = Verification("m", parts + (MasterPart("3", Status.PASS, Status.PASS, off=("crazing (0.50 of its size "
                                                                                        "off)",)),))
        assert "the detector's boxes on 1's pit (0.40 of its size off), 3's crazing (0.50 of its size off) lie more " \
               "than a third off their defects" in two.summary()

    def test_verify_holds_each_defects_box_against_its_label(self):
        labels = json.loads((FIXTURE / "labels" / "000003.json").read_text())
        frames = [type("Frame", (), {"frame_id": "000003"})()]

        def moved(item):  # each labelled defect boxed half its width to the right
            return Verdict(Status.REJECT), [((d["box"][0] + (d["box"][2] - d["box"][0]) / 2, d["box"][1],
                                              d["box"][2] + (d["box"][2] - d["box"][0]) / 2, d["box"][3]),
                                             Status.REJECT) for d in labels["defects"]]

        (part,) = verify(FIXTURE, frames, moved, BOTH_WAYS).parts
        assert part.off == tuple(f"{d['class']} (0.50 of its size off)" for d in labels["defects"])
        (part,) = verify(FIXTURE, frames, lambda item: (Verdict(Status.REJECT), [(tuple(d["box"]), Status.REJECT)
                                                                                 for d in labels["defects"]]),
                         BOTH_WAYS).parts
        assert part.off == ()


class TestMissedDefects:
    DEFECT = {"class": "pit", "box": [100, 100, 140, 120], "deviation_mm": 2.0}

    @pytest.mark.parametrize("status", [Status.REJECT, Status.FLAG, Status.ERROR])
    def test_a_box_of_its_own_that_keeps_the_part_off_the_line(self, status):
        assert missed_defects([self.DEFECT], [((104.0, 102.0, 146.0, 124.0), status)]) == []

    def test_a_box_of_its_own_that_passes_it(self):
        assert missed_defects([self.DEFECT], [((104.0, 102.0, 146.0, 124.0), Status.PASS)]) == [
            "pit at (100, 100)-(140, 120)"]

    def test_a_box_that_overlaps_it_too_little(self):
        # IoU 0.25: another place on the plate
        assert missed_defects([self.DEFECT], [((124.0, 100.0, 164.0, 120.0), Status.REJECT)]) == [
            "pit at (100, 100)-(140, 120)"]

    def test_one_rejecting_box_of_several_is_enough(self):
        boxes = [((100.0, 100.0, 140.0, 120.0), Status.PASS), ((98.0, 99.0, 139.0, 121.0), Status.REJECT)]
        assert missed_defects([self.DEFECT], boxes) == []

    def test_beyond_a_limit_lists_the_defects_a_part_is_rejected_for(self):
        labels = _labels(("pit", 0.2), ("pit", 1.6), ("pit", 1.1), ("pit", -1.4))
        assert [d["deviation_mm"] for d in beyond_a_limit(labels, BOTH_WAYS)] == [1.6, -1.4]


def _run_demo(tmp_path, *sets: str):
    return cli("run", str(DEMO), "--set", f"results.path={tmp_path / 'results'}",
               "--set", f"outputs=[{{plugin: log, settings: {{file: {tmp_path / 'rejects.log'}}}}}]", *sets)


def test_a_detector_made_blind_by_its_confidence_keeps_the_line_from_starting(tmp_path):
    """At confidence 0.9 the demo's detector finds nothing, and before master parts every plate passed."""
    out = _run_demo(tmp_path, "--set", "detector.confidence=0.9")
    assert out.returncode == 4, out.stdout + out.stderr
    assert ("ALARM verify: 3 master parts with a defect beyond a limit passed (frames 000003, 000006, 000009 of "
            f"{MASTERS})") in out.stdout
    assert "parts 0  passed 0" in out.stdout  # no plate was read
    assert f"`inspect eval depth {MASTERS} --recipe {DEMO} --boxes detector`" in out.stdout  # where to look
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    assert db.execute("SELECT COUNT(*) FROM parts").fetchone()[0] == 0
    (message,) = db.execute("SELECT message FROM alarms WHERE source = 'verify'").fetchone()
    assert message.startswith("3 master parts with a defect beyond a limit passed")
    assert db.execute("SELECT exit_code FROM runs").fetchone()[0] == 4
    report = cli_here("report", str(tmp_path / "results")).stdout
    assert "run 1 did not start: 3 master parts with a defect beyond a limit passed" in report


def test_master_parts_all_in_error_keep_the_line_from_starting(tmp_path):
    """A blind detector on plates outside the working distance: every master part an ERROR, which had counted
    as rejected."""
    out = _run_demo(tmp_path, "--set", "detector.confidence=0.9", "--set", "stereo.working_distance_mm=[600,700]")
    assert out.returncode == 4, out.stdout + out.stderr
    assert (f"ALARM verify: none of the 3 defective master parts of {MASTERS} could be inspected (frame 000003: no "
            f"defect found, but the images show the plate at 98 px of disparity") in out.stdout
    assert "parts 0  passed 0" in out.stdout


def test_a_master_part_whose_image_cannot_be_decoded_is_counted_an_error_not_a_pass(tmp_path):
    masters = tmp_path / "masters"
    shutil.copytree(MASTERS, masters)
    image = masters / "right" / "000003.jpg"
    cv2.imwrite(str(image), cv2.imread(str(image))[:100, :100])  # whole, but not the calibration's size
    out = _run_demo(tmp_path, "--set", f"verify.path={masters}", "--set", "camera.settings.max_frames=1")
    assert out.returncode == 0, out.stdout + out.stderr
    assert "3 of 3 defective ones rejected" in out.stdout and "1 could not be inspected (ERROR)" in out.stdout
    report = cli_here("report", str(tmp_path / "results")).stdout  # which run was checked, and how
    assert f"run 1 checked its master parts {masters}: 4 inspected, 3 of 3 defective" in report


def test_labels_that_become_unreadable_after_the_recipe_was_loaded_keep_the_line_from_starting(tmp_path):
    from core import engine
    from core.recipe import load_recipe

    masters = tmp_path / "masters"
    shutil.copytree(MASTERS, masters)
    loaded = load_recipe(DEMO, overrides=[f"verify.path={masters}", f"results.path={tmp_path / 'results'}",
                                          f"outputs=[{{plugin: log, settings: {{file: {tmp_path / 'rejects.log'}}}}}]"])
    (masters / "labels" / "000006.json").write_text("{")
    summary = engine.run(loaded, device="cpu")
    assert summary.frames == 0 and summary.exit_code == engine.EXIT_ALARMS
    (alarm,) = summary.alarms
    assert alarm.source == "verify" and "could not be inspected" in alarm.message and "000006.json" in alarm.message


class TestRecipe:
    def test_validate_says_how_many_master_parts_and_how_many_defective(self):
        assert cli_here("validate", str(DEMO)).stdout.rstrip().endswith(", master parts 4 (3 defective))")
        assert cli_here("validate", str(DEMO), "--set", "verify.path=null").stdout.rstrip().endswith(
            ", no master parts)")

    def test_a_missing_folder_is_named_at_its_key(self, tmp_path):
        out = cli_here("validate", str(DEMO), "--set", f"verify.path={tmp_path / 'nope'}")
        assert out.returncode == 2
        assert out.stderr.strip().endswith(f"verify.path: sequence folder not found: {tmp_path / 'nope'}")

    def test_a_master_image_cut_short_is_named(self, tmp_path):
        masters = tmp_path / "masters"
        shutil.copytree(MASTERS, masters)
        image = masters / "right" / "000003.jpg"
        image.write_bytes(image.read_bytes()[:1000])
        out = cli_here("validate", str(DEMO), "--set", f"verify.path={masters}")
        assert out.returncode == 2 and "verify.path" in out.stderr and "000003" in out.stderr

    def test_a_frame_without_labels_is_named(self, tmp_path):
        masters = tmp_path / "masters"
        shutil.copytree(MASTERS, masters)
        (masters / "labels" / "000004.json").unlink()
        out = cli_here("validate", str(DEMO), "--set", f"verify.path={masters}")
        assert out.returncode == 2 and "verify.path" in out.stderr and "000004" in out.stderr

    def test_labels_without_their_frames_images_are_named(self, tmp_path):
        """Their part would not be inspected, and the check would vouch for it all the same."""
        masters = tmp_path / "masters"
        shutil.copytree(MASTERS, masters)
        shutil.copy(masters / "labels" / "000003.json", masters / "labels" / "000099.json")
        out = cli_here("validate", str(DEMO), "--set", f"verify.path={masters}")
        assert out.returncode == 2
        assert out.stderr.strip().endswith(f"verify.path: {masters / 'labels' / '000099.json'}: no left/ or right/ "
                                           f"image of that frame")

    def test_a_recipe_without_master_parts_is_warned_of(self):
        out = cli_here("validate", str(DEMO), "--set", "verify.path=null")
        assert out.returncode == 0
        assert out.stderr.strip().endswith("verify.path: warning: no master parts: a detector that finds nothing "
                                           "(weights that score low, a confidence set too high) passes every part "
                                           "unnoticed; name a recording of known parts (docs/recipe-reference.md, "
                                           "verify)")

    def test_master_parts_none_of_which_is_defective_are_warned_of(self, tmp_path):
        masters = tmp_path / "masters"
        shutil.copytree(MASTERS, masters)
        for path in (masters / "labels").glob("*.json"):
            labels = json.loads(path.read_text())
            labels["defects"] = [dict(d, deviation_mm=0.1) for d in labels["defects"]]
            path.write_text(json.dumps(labels))
        out = cli_here("validate", str(DEMO), "--set", f"verify.path={masters}")
        assert out.returncode == 0
        assert "verify.path: warning: none of the 4 parts" in out.stderr
        assert "verify.path" not in cli_here("validate", str(DEMO)).stderr


def test_ctrl_c_while_the_master_parts_are_inspected_ends_the_run_finished_without_a_plate(tmp_path):
    """Ctrl-C before the first plate (the model loading, the master parts) went past the run's finalising: its
    outputs were not closed and the store kept it as running, a crash for the next run to report."""
    masters = tmp_path / "masters"
    for copy in range(3):  # 30 master parts: several seconds to interrupt them in
        for frame in sorted((FIXTURE / "left").glob("*.jpg")):
            name = f"{copy}{frame.stem}"
            for eye in ("left", "right"):
                (masters / eye).mkdir(parents=True, exist_ok=True)
                shutil.copy(FIXTURE / eye / frame.name, masters / eye / f"{name}.jpg")
            (masters / "labels").mkdir(exist_ok=True)
            shutil.copy(FIXTURE / "labels" / f"{frame.stem}.json", masters / "labels" / f"{name}.json")
    shutil.copy(FIXTURE / "calib.yaml", masters / "calib.yaml")
    results = tmp_path / "results"
    exe = Path(sys.executable).parent / "inspect"
    proc = subprocess.Popen([str(exe), "run", str(DEMO), "--quiet", "--set", f"results.path={results}",
                             "--set", f"outputs=[{{plugin: log, settings: {{file: {tmp_path / 'rejects.log'}}}}}]",
                             "--set", f"verify.path={masters}"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:  # the run is in the store: its start is under way
        try:
            with sqlite3.connect(results / "results.db", timeout=1) as db:
                if db.execute("SELECT COUNT(*) FROM runs").fetchone()[0]:
                    break
        except sqlite3.Error:
            pass
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in err, out + err
    db = sqlite3.connect(results / "results.db")
    assert db.execute("SELECT status, exit_code FROM runs").fetchone() == ("finished", 130)
    assert db.execute("SELECT COUNT(*) FROM parts").fetchone()[0] == 0


def _recording(tmp_path) -> Path:
    """The demo's master parts as `inspect camera record` would leave them: images and calibration, no labels."""
    folder = tmp_path / "recording"
    shutil.copytree(MASTERS, folder)  # the links followed: files of their own
    shutil.rmtree(folder / "labels")
    return folder


class TestDraftLabels:
    def test_the_detectors_boxes_are_drafted_with_their_depths_left_to_measure(self, tmp_path):
        from drivers.sequence_folder import read_labels

        folder = _recording(tmp_path)
        out = cli("data", "draft-labels", str(folder))  # the console script, once
        assert out.returncode == 0, out.stdout + out.stderr
        assert out.stdout.startswith("wrote 4 labels (") and "deviation_mm as measured on the plate" in out.stdout
        drafted = {p.stem: read_labels(p, (376, 672)) for p in sorted((folder / "labels").glob("*.json"))}
        assert sorted(drafted) == ["000003", "000004", "000006", "000009"]
        assert all(d["deviation_mm"] is None for labels in drafted.values() for d in labels["defects"])
        truth = json.loads((FIXTURE / "labels" / "000006.json").read_text())["defects"][0]
        (found,) = drafted["000006"]["defects"]  # the pit the detector finds, in its own box
        assert found["class"] == truth["class"] and abs(found["box"][0] - truth["box"][0]) < 10
        # undecided until measured: the check would vouch for nothing, and says so
        warned = cli_here("validate", str(DEMO), "--set", f"verify.path={folder}")
        assert "master parts 4 (0 defective)" in warned.stdout and "verify.path: warning: none of the 4" in warned.stderr
        labels = json.loads((folder / "labels" / "000006.json").read_text())
        labels["defects"][0]["deviation_mm"] = 2.88  # measured on the plate
        (folder / "labels" / "000006.json").write_text(json.dumps(labels))
        assert "master parts 4 (1 defective)" in cli_here("validate", str(DEMO), "--set", f"verify.path={folder}").stdout

    def test_labels_already_there_are_left_as_they_were(self, tmp_path):
        folder = _recording(tmp_path)
        (folder / "labels").mkdir()
        mine = '{"defects": [{"class": "pit", "box": [1, 1, 20, 20], "deviation_mm": 1.9}]}'
        (folder / "labels" / "000003.json").write_text(mine)
        out = cli_here("data", "draft-labels", str(folder))
        assert "wrote 3 labels" in out.stdout and "1 frames already labelled, left as they were" in out.stdout
        assert (folder / "labels" / "000003.json").read_text() == mine
        again = cli_here("data", "draft-labels", str(folder))
        assert again.returncode == 0 and "every frame is labelled already; nothing written" in again.stdout

    def test_a_frame_that_cannot_be_read_writes_nothing(self, tmp_path):
        folder = _recording(tmp_path)
        image = folder / "right" / "000006.jpg"
        cv2.imwrite(str(image), cv2.imread(str(image))[:100, :100])
        out = cli_here("data", "draft-labels", str(folder))
        assert out.returncode == 2 and "000006" in out.stderr and len(out.stderr.strip().splitlines()) == 1
        assert not (folder / "labels").exists()
        assert cli_here("data", "draft-labels", str(tmp_path / "nope")).stderr.strip() == \
            f"error: {tmp_path / 'nope'}: not a sequence folder"
        for eye in ("left", "right"):  # a recording without frames
            shutil.rmtree(folder / eye)
            (folder / eye).mkdir()
        assert cli_here("data", "draft-labels", str(folder)).stderr.strip() == f"error: {folder}: no frames in left/"
