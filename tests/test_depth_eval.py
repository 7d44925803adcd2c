"""``inspect eval depth`` on the committed evaluation sequences, and the figures it is made of."""
from __future__ import annotations

import dataclasses
import json
import math
import re
import shutil

import cv2
import numpy as np
import pytest
from conftest import ROOT, cli, cli_here

from core import depth_eval as ev, uncertainty_budget
from core.depth import DepthRule, ring_mask, roi_box
from core.types import Calibration

TEXTURED = ROOT / "sim_fixtures" / "plates_textured"
LOW_TEXTURE = ROOT / "sim_fixtures" / "plates_low_texture"
RANGE = "stereo.working_distance_mm=[300,700]"  # the sequences span 350-650 mm; the demo recipe 350-500


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory):
    out = tmp_path_factory.mktemp("depth_eval")
    result = cli("eval", "depth", str(TEXTURED), str(LOW_TEXTURE), "--set", RANGE, "--out", str(out), "--threads", "1")
    return result, out


def test_writes_json_markdown_and_figure(evaluated):
    result, out = evaluated
    assert result.returncode == 0, result.stderr
    body = json.loads((out / "depth_eval.json").read_text())
    assert set(body["sequences"]) == {"plates_textured", "plates_low_texture"}
    assert body["method"] == "surface" and body["backend"] == "torch_sgm" and "cores" in body["machine"]
    assert (out / "depth_eval.png").stat().st_size > 10_000
    table = (out / "depth_eval.md").read_text()
    assert "| all | surface |" in table and "| all | disparity (reference) |" in table and "true \\ measured" in table
    assert re.search(r"the texture's floor lies a median \d\.\d\dx higher", table)
    assert table in result.stdout
    # one line per defect: truth, measurement with its uncertainty, both decisions
    lines = [line for line in result.stdout.splitlines() if re.match(r"plates_\w+ \d{6} ", line)]
    assert len(lines) == len(body["rows"]) == 11 and all(" true " in line and "measured" in line for line in lines)
    # a defect no rule could decide says what its uncertainty was mostly made of
    undecided = {(r["sequence"], r["frame_id"], r["uncertainty_from"]) for r in body["rows"] if r["proven"] == "undecided"}
    said = {(line.split()[0], line.split()[1], line.split("undecided: mostly ")[1].split(";")[0])
            for line in lines if "undecided: mostly " in line}
    assert said == {(s, f, uncertainty_budget.KINDS[k]) for s, f, k in undecided}
    # every frame lies within the working distance: none would make a part without defects an ERROR
    assert body["plate_check"]["frames"] > 0 and body["plate_check"]["flagged"] == []
    assert f"0 of {body['plate_check']['frames']} frames show the plate outside" in table
    # the depth time per defect, and the reference's within it: the surface fit's own work is the rest
    assert body["seconds_per_defect"] > 0 and body["reference_seconds_per_defect"] > 0
    assert re.search(r"Depth per defect \(surface\): \d+\.\d ms on this machine; the reference, the backend's plane "
                     r"and median alone, \d+\.\d ms\.", table)
    # each class of the labels on its own, every defect in one of them
    assert set(body["classes"]) == {"crazing", "inclusion", "pitted_surface", "scratches"}
    assert sum(c["defects"] for c in body["classes"].values()) == len(body["rows"])
    assert all(f"\n| {name} | {c['defects']} ({c['measured']}) |" in table for name, c in body["classes"].items())


def test_the_surface_fit_beats_the_backend_alone_and_states_its_uncertainty(evaluated):
    _, out = evaluated
    body = json.loads((out / "depth_eval.json").read_text())
    surface, reference = body["all"]["measurement"], body["all"]["reference"]
    assert surface["measured"] == surface["defects"] == 11
    assert surface["deviation_error_mm"]["median"] < 0.5 * reference["deviation_error_mm"]["median"]
    assert surface["deviation_error_mm"]["p90"] < 0.6 * reference["deviation_error_mm"]["p90"]
    assert surface["distance_error_percent"]["median"] < 0.05
    assert 0.85 <= surface["ratio_median"] <= 1.15
    assert surface["within_2_sigma"] >= 0.7  # 11 defects: the suite's check, not the benchmark (docs/benchmarks.md)
    assert surface["clear_cut_wrong"] == 0
    rows = body["rows"]
    assert all(r["floor_mm"] > 0 and r["deviation_sigma_mm"] > 0 for r in rows)
    # the distance's floor is the region's alone, below the deviation's, which holds the ring's too
    assert all(0 < r["distance_floor_mm"] < r["floor_mm"] for r in rows)
    assert surface["distance_over_floor_per_defect"] > 0 and reference["distance_over_floor_per_defect"] > 0
    # the texture's floor lies above the floor, so the error is nearer it
    assert all(r["texture_floor_mm"] > r["floor_mm"] and r["texture_distance_floor_mm"] > r["distance_floor_mm"]
               for r in rows)
    assert surface["texture_floor_over_floor_median"] > 1
    assert surface["error_over_texture_floor_per_defect"] < surface["error_over_floor_per_defect"]
    assert surface["sigma_over_texture_floor_median"] < surface["sigma_over_floor_median"]
    assert sum(sum(by.values()) for by in surface["confusion"].values()) == len(rows)
    # each measurement's largest part of its uncertainty, and of those left undecided a tally by it
    assert all(r["uncertainty_from"] in uncertainty_budget.KINDS for r in rows)
    undecided = sum(by.get("undecided", 0) for by in surface["confusion"].values())
    assert sum(sum(by.values()) for by in surface["undecided_from"].values()) == undecided
    assert ("undecided defects' uncertainty mostly came from" in (out / "depth_eval.md").read_text()) == (undecided > 0)


def test_with_the_true_disparity_each_error_splits_into_the_rings_the_regions_and_its_extents(evaluated):
    _, out = evaluated
    body = json.loads((out / "depth_eval.json").read_text())
    rows = body["rows"]
    for r in rows:
        parts = r["error_ring_mm"] + r["error_region_mm"] + r["error_extent_mm"]
        assert parts == pytest.approx(r["deviation_mm"] - r["true_deviation_mm"], abs=1e-6)
    # sloped walls over the outer 45 % of each half-size (sim.scene): the box's central 60 % holds a little of them
    assert all(abs(r["error_extent_mm"]) < 0.1 * abs(r["true_deviation_mm"]) + 0.02 for r in rows)
    summary = body["all"]["measurement"]["error_parts"]
    assert summary["defects"] == len(rows)
    assert sum(summary[name]["share"] for name in ("ring", "region", "extent")) == pytest.approx(1.0)
    assert "error_parts" not in body["all"]["reference"] or not body["all"]["reference"]["error_parts"]
    table = (out / "depth_eval.md").read_text()
    assert re.search(r"Where the error comes from \(the frames' true disparity, 11 of the 11 measured defects.*"
                     r"the ring's plane [\d.]+ / [\d.]+ \(\d+ %\)", table)


def test_a_sequence_without_labels_is_a_one_line_error(tmp_path):
    copy = tmp_path / "seq"
    shutil.copytree(TEXTURED, copy)
    shutil.rmtree(copy / "labels")
    result = cli_here("eval", "depth", str(copy), "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "labels/000000.json" in lines[0]
    assert cli_here("eval", "depth", str(tmp_path / "nowhere")).returncode == 2


def test_a_sequence_given_twice_is_an_error_not_counted_twice(tmp_path):
    result = cli_here("eval", "depth", str(TEXTURED), str(TEXTURED) + "/", "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    assert result.stderr == f"error: {TEXTURED}: given twice (also as {TEXTURED})\n"


def test_labelled_defects_without_a_truth_are_counted_as_not_scored(evaluated, tmp_path):
    # the generator writes a null deviation where the truth cannot be measured (a defect out of the right
    # camera's view): leaving it out of the figures must be said, not left for the reader to count
    copy = tmp_path / "seq"
    shutil.copytree(TEXTURED, copy)
    path = copy / "labels" / "000000.json"
    labels = json.loads(path.read_text())
    labels["defects"][0]["deviation_mm"] = None
    path.write_text(json.dumps(labels))
    result = cli("eval", "depth", str(copy), "--set", RANGE, "--out", str(tmp_path / "out"), "--threads", "1",
                 "--no-figure")
    assert result.returncode == 0, result.stderr
    assert "Not scored: 1 labelled defect(s) whose labels give no true deviation" in result.stdout
    body = json.loads((tmp_path / "out" / "depth_eval.json").read_text())
    whole = json.loads((evaluated[1] / "depth_eval.json").read_text())
    assert body["unscored"] == 1 and whole["unscored"] == 0
    assert body["all"]["measurement"]["defects"] == whole["sequences"]["plates_textured"]["measurement"]["defects"] - 1


def test_labels_that_give_a_deviation_and_no_distance_score_the_deviation(evaluated, tmp_path):
    # another renderer's labels may state a pit's depth alone: its defects were all left out as not scored
    copy = tmp_path / "seq"
    shutil.copytree(TEXTURED, copy)
    for path in sorted((copy / "labels").glob("*.json")):
        labels = json.loads(path.read_text())
        for defect in labels["defects"]:
            defect.pop("distance_mm", None)
        path.write_text(json.dumps(labels))
    result = cli("eval", "depth", str(copy), "--set", RANGE, "--out", str(tmp_path / "out"), "--threads", "1")
    assert result.returncode == 0, result.stderr
    assert "Not scored" not in result.stdout and " Z    n/a true " in result.stdout
    body = json.loads((tmp_path / "out" / "depth_eval.json").read_text())["all"]["measurement"]
    whole = json.loads((evaluated[1] / "depth_eval.json").read_text())["sequences"]["plates_textured"]["measurement"]
    assert body["defects"] == whole["defects"] and body["measured"] == whole["measured"]
    assert body["deviation_error_mm"] == whole["deviation_error_mm"]
    # the floor at the measured distance instead of the true one: within a part in a thousand of it
    assert body["floor_mm"]["median"] == pytest.approx(whole["floor_mm"]["median"], rel=2e-3)
    assert not body["distance_error_mm"]
    assert (tmp_path / "out" / "depth_eval.png").stat().st_size > 0


def test_a_broken_frame_anywhere_is_named_before_any_frame_is_matched(tmp_path):
    # the last frame's labels and the middle frame's right image broken: both found from the files, and the
    # first named with a count of the rest, before a frame is matched (no line per defect, nothing written)
    copy = tmp_path / "seq"
    shutil.copytree(TEXTURED, copy)
    (copy / "labels" / "000002.json").write_text('{"defects": [{"class": "crazing", "box": [1, 2, 3]}]}')
    right = copy / "right" / "000001.jpg"
    right.write_bytes(right.read_bytes()[:2000])
    result = cli_here("eval", "depth", str(copy), "--out", str(tmp_path / "out"))
    assert result.returncode == 2 and result.stdout == ""
    assert result.stderr.strip() == (f"error: {right}: right image of frame 000001 is not whole: truncated JPEG "
                                     f"(no end-of-image marker) (and 1 more frame)")
    assert not any((tmp_path / "out").iterdir())


@pytest.mark.parametrize("calibration", [None, "fx: [\n"], ids=["missing", "not YAML"])
def test_a_sequence_with_a_bad_calibration_is_a_one_line_error_naming_the_file(tmp_path, calibration):
    copy = tmp_path / "seq"
    shutil.copytree(TEXTURED, copy)
    if calibration is None:
        (copy / "calib.yaml").unlink()
    else:
        (copy / "calib.yaml").write_text(calibration)
    result = cli_here("eval", "depth", str(copy), "--out", str(tmp_path / "out"))
    assert result.returncode == 2
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: {copy}") and "calib.yaml" in lines[0], lines


class TestBoxError:
    def test_no_error_leaves_the_box_as_it_is(self):
        assert ev.BoxError().apply((10, 20, 50, 40), "a/000000/0") == (10.0, 20.0, 50.0, 40.0)

    def test_scale_keeps_the_centre_and_scales_the_sides(self):
        x0, y0, x1, y1 = ev.BoxError(scale=1.5).apply((10, 20, 50, 40), "a/000000/0")
        assert (x0 + x1, y0 + y1) == pytest.approx((60.0, 60.0))
        assert (x1 - x0, y1 - y0) == pytest.approx((60.0, 30.0))

    def test_shift_moves_by_its_share_of_the_size_in_a_direction_per_defect(self):
        error = ev.BoxError(shift=0.2)
        moved = [error.apply((0, 0, 40, 20), f"a/000000/{i}") for i in range(8)]
        assert moved[0] == error.apply((0, 0, 40, 20), "a/000000/0")  # the same defect moves the same way
        offsets = np.array([((b[0] + b[2]) / 2 - 20, (b[1] + b[3]) / 2 - 10) for b in moved])
        # the offset lies on the ellipse of 0.2 of the width and 0.2 of the height
        assert np.hypot(offsets[:, 0] / 8.0, offsets[:, 1] / 4.0) == pytest.approx(np.ones(8))
        assert len({(round(x), round(y)) for x, y in offsets}) > 4  # directions differ between defects
        assert all(b[2] - b[0] == pytest.approx(40) and b[3] - b[1] == pytest.approx(20) for b in moved)


def test_boxes_that_are_off_are_measured_there_with_the_true_boxs_floor(evaluated, tmp_path):
    _, out = evaluated
    result = cli("eval", "depth", str(TEXTURED), "--set", RANGE, "--out", str(tmp_path), "--threads", "1",
                 "--box-scale", "1.3", "--box-shift", "0.15", "--no-figure", "--quiet")
    assert result.returncode == 0, result.stderr
    moved = json.loads((tmp_path / "depth_eval.json").read_text())
    true = {(r["frame_id"], tuple(r["box"])): r for r in json.loads((out / "depth_eval.json").read_text())["rows"]}
    assert moved["box_scale"] == 1.3 and moved["box_shift"] == 0.15 and "scaled by 1.3" in result.stdout
    for r in moved["rows"]:
        same = true[(r["frame_id"], tuple(r["box"]))]  # rows keep the true box
        assert r["floor_mm"] == pytest.approx(same["floor_mm"])
        # and the box measured in, against it, in the options' own measures
        assert (r["box_shift"], r["box_scale"]) == pytest.approx((0.15, 1.3)) and same["box_shift"] == 0
    assert any(r["deviation_mm"] != true[(r["frame_id"], tuple(r["box"]))]["deviation_mm"] for r in moved["rows"])
    assert cli_here("eval", "depth", str(TEXTURED), "--box-scale", "nan").returncode == 2


def test_a_moved_box_s_distance_is_scored_where_it_looks_and_unscored_without_the_true_disparity(evaluated, tmp_path):
    # the plates are tilted: a box moved off its defect measures the surface's distance at another place
    _, out = evaluated
    true = {(r["frame_id"], tuple(r["box"])): r for r in json.loads((out / "depth_eval.json").read_text())["rows"]
            if r["sequence"] == TEXTURED.name}
    assert cli("eval", "depth", str(TEXTURED), "--set", RANGE, "--out", str(tmp_path / "moved"), "--threads", "1",
               "--box-shift", "0.15", "--no-figure", "--quiet").returncode == 0
    moved = json.loads((tmp_path / "moved" / "depth_eval.json").read_text())["rows"]
    moves = [abs(r["true_distance_mm"] - true[(r["frame_id"], tuple(r["box"]))]["true_distance_mm"]) for r in moved]
    assert 0 < max(moves) < 10
    # without the true disparity the moved point has no truth: the distance goes unscored, the deviation not
    bare = tmp_path / "bare"
    shutil.copytree(TEXTURED, bare)
    shutil.rmtree(bare / "gt")
    assert cli("eval", "depth", str(bare), "--set", RANGE, "--out", str(tmp_path / "bare_out"), "--threads", "1",
               "--box-shift", "0.15", "--no-figure", "--quiet").returncode == 0
    body = json.loads((tmp_path / "bare_out" / "depth_eval.json").read_text())
    assert all(r["true_distance_mm"] is None for r in body["rows"])
    assert body["all"]["measurement"]["deviation_error_mm"] and not body["all"]["measurement"]["distance_error_mm"]
    # a true disparity that cannot be read is a one-line error naming it, not a distance quietly unscored
    (bare / "gt").mkdir()
    broken = bare / "gt" / sorted(p.name for p in (TEXTURED / "gt").glob("*.png"))[0]
    broken.write_bytes(b"not a png")
    result = cli_here("eval", "depth", str(bare), "--set", RANGE, "--out", str(tmp_path / "broken"), "--threads", "1",
                      "--box-shift", "0.15", "--no-figure", "--quiet")
    assert result.returncode == 2 and str(broken) in result.stderr and "Traceback" not in result.stderr, result.stderr
    # nor is one of another size than the images, whose pixels would be another place's
    cv2.imwrite(str(broken), np.full((20, 30), 256 * 60, np.uint16))
    result = cli_here("eval", "depth", str(bare), "--set", RANGE, "--out", str(tmp_path / "small"), "--threads", "1",
                      "--box-shift", "0.15", "--no-figure", "--quiet")
    assert result.returncode == 2 and str(broken) in result.stderr and "30x20" in result.stderr, result.stderr


class TestDistanceAtBox:
    CALIB = Calibration(700.0, 120.0, 159.5, 119.5, 320, 240)

    @staticmethod
    def plate(u, v):
        return 60.0 + 0.05 * u - 0.02 * v

    def disparity(self):
        v, u = np.mgrid[0:240, 0:320].astype(np.float64)
        d = self.plate(u, v)
        d[100:130, 100:140] -= 0.4  # the defect itself, inside its box
        d[80:95, 150:170] += 2.0  # another defect across the ring
        d[:, :20] = np.nan  # unknown where the left eye alone looks
        return d

    def test_the_distance_moves_along_the_plate_s_plane_to_the_box_s_centre(self):
        true_box, box = (100.0, 100.0, 140.0, 130.0), (106.0, 96.0, 146.0, 126.0)
        true_distance = float(self.CALIB.distance_mm(self.plate(120.0, 115.0) - 0.4))
        moved = ev.distance_at_box(true_distance, self.disparity(), self.CALIB, true_box, box, DepthRule())
        expected = float(self.CALIB.distance_mm(self.plate(126.0, 111.0) - 0.4))
        assert moved == pytest.approx(expected, abs=1e-6)
        assert abs(moved - true_distance) > 0.5  # the plate's tilt moves it by millimetres

    def test_a_box_that_stays_keeps_the_distance(self):
        box = (100.0, 100.0, 140.0, 130.0)
        assert ev.distance_at_box(500.0, self.disparity(), self.CALIB, box, box, DepthRule()) == pytest.approx(500.0)

    def test_no_truth_where_the_ring_is_unknown(self):
        unknown = np.full((240, 320), np.nan)
        box = (100.0, 100.0, 140.0, 130.0)
        assert ev.distance_at_box(500.0, unknown, self.CALIB, box, box, DepthRule()) is None


DEMO = ROOT / "sim_fixtures" / "steel_plate"


def test_the_detectors_boxes_are_measured_and_the_defects_it_missed_counted(tmp_path):
    result = cli("eval", "depth", str(DEMO), "--boxes", "detector", "--out", str(tmp_path), "--threads", "1",
                 "--no-figure")
    assert result.returncode == 0, result.stderr
    body = json.loads((tmp_path / "depth_eval.json").read_text())
    s = body["all"]["measurement"]
    missed = [r for r in body["rows"] if r["status"] == ev.MISSED]
    assert body["boxes"] == "detector" and s["missed"] == len(missed)
    assert all(r["deviation_mm"] is None and r["note"] == "missed by the detector" for r in missed)
    assert 0 < s["measured"] <= s["defects"] - s["missed"]  # the demo's detector finds most of its defects
    assert f"{s['defects'] - s['missed']} of the {s['defects']} labelled defects boxed" in result.stdout
    # where the detector's boxes lie, from the rows of the defects it boxed
    placed = [r["box_shift"] for r in body["rows"] if r["status"] != ev.MISSED]
    assert all(r["box_shift"] is None for r in missed) and s["box_shift"]["max"] == pytest.approx(max(placed))
    assert s["boxes_beyond"]["tenth"] == sum(x > 0.1 for x in placed) and 0 < s["box_shift"]["median"] < 0.1
    assert f"Its boxes lie a median {s['box_shift']['median']:.2f} of their defect's size off its centre" in result.stdout
    # rows keep the true boxes; a measured one was measured in a box of the detector's, not the true one
    assert cli("eval", "depth", str(DEMO), "--out", str(tmp_path / "true"), "--threads", "1", "--no-figure",
               "--quiet").returncode == 0
    true_run = json.loads((tmp_path / "true" / "depth_eval.json").read_text())
    by_box = {(r["frame_id"], tuple(r["box"])): r for r in true_run["rows"]}
    measured = [r for r in body["rows"] if r["deviation_mm"] is not None]
    assert all((r["frame_id"], tuple(r["box"])) in by_box for r in body["rows"])
    assert any(r["deviation_mm"] != by_box[(r["frame_id"], tuple(r["box"]))]["deviation_mm"] for r in measured)


def test_a_detector_that_finds_nothing_leaves_every_defect_missed(tmp_path):
    result = cli("eval", "depth", str(DEMO), "--boxes", "detector", "--set", "detector.confidence=1.0",
                 "--out", str(tmp_path), "--threads", "1", "--quiet")
    assert result.returncode == 0, result.stderr
    s = json.loads((tmp_path / "depth_eval.json").read_text())["all"]["measurement"]
    assert s["measured"] == 0 and s["missed"] == s["defects"] > 0 and s["missed_beyond_a_limit"] > 0
    assert not (tmp_path / "depth_eval.png").exists()  # nothing to plot


def test_a_detector_that_fails_on_a_frame_is_a_one_line_error_naming_it(tmp_path):
    # on the line such a frame is an ERROR part; here it ended the evaluation in a traceback
    result = cli_here("eval", "depth", str(DEMO), "--boxes", "detector", "--set", "detector.settings.max_det=1",
                      "--out", str(tmp_path), "--threads", "1", "--quiet")
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert re.search(r"frame \d{6}: detection failed: DetectionLimit: the detector reached its max_det of 1 boxes",
                     result.stderr), result.stderr


def test_box_changes_and_the_detectors_boxes_do_not_mix(tmp_path):
    result = cli_here("eval", "depth", str(DEMO), "--boxes", "detector", "--box-shift", "0.1", "--out", str(tmp_path))
    assert result.returncode == 2 and "--boxes detector" in result.stderr


class TestFloor:
    def test_the_floor_falls_with_the_gradient_energy(self):
        rng = np.random.default_rng(0)
        grey = rng.normal(100, 10, (40, 60)).astype(np.float32)
        mask = np.zeros(grey.shape, bool)
        mask[10:20, 10:30] = True
        gx = 0.5 * (grey[:, 2:] - grey[:, :-2])
        expected = 2.0 * math.sqrt(2) / math.sqrt(float(np.sum(gx[10:20, 9:29] ** 2)))
        assert ev.floor_px(grey, mask, 2.0) == pytest.approx(expected, rel=1e-5)
        assert ev.floor_px(2 * grey, mask, 2.0) == pytest.approx(expected / 2, rel=1e-5)
        assert ev.floor_px(np.full((40, 60), 5.0, np.float32), mask, 2.0) == math.inf

    def test_the_texture_s_floor_leaves_out_the_noise_s_own_gradient_energy(self):
        # a faint texture under noise: the noisy image's sum of I_x^2 is the texture's and the noise's, and the
        # texture's floor is the floor of the same texture drawn without noise
        rng = np.random.default_rng(2)
        texture = cv2.GaussianBlur(rng.normal(0, 6, (200, 300)).astype(np.float32), (0, 0), 1.0) + 100
        noisy = texture + rng.normal(0, 2.0, texture.shape).astype(np.float32)
        mask = np.zeros(texture.shape, bool)
        mask[20:180, 20:280] = True
        clean = ev.floor_px(texture, mask, 2.0)
        assert ev.floor_px(noisy, mask, 2.0) < 0.9 * clean  # the noise counted as texture: too low a floor
        assert ev.floor_px(noisy, mask, 2.0, texture_only=True) == pytest.approx(clean, rel=0.03)
        # noise alone leaves (about) nothing to match on: no floor, or one far above any texture's
        flat = np.full(texture.shape, 100, np.float32) + rng.normal(0, 2.0, texture.shape).astype(np.float32)
        assert ev.floor_px(flat, mask, 2.0, texture_only=True) > 5 * ev.floor_px(flat, mask, 2.0)

    def test_the_distance_s_floor_is_the_region_s_and_the_deviation_s_adds_the_ring_s(self):
        rng = np.random.default_rng(1)
        grey = rng.normal(100, 10, (120, 160)).astype(np.float32)
        calib = Calibration(focal_px=350.0, baseline_mm=120.0, cx=80.0, cy=60.0, width=160, height=120)
        box, rule = (60.0, 40.0, 100.0, 80.0), DepthRule()
        deviation, distance = ev.defect_floors_mm(grey, box, calib, rule, 2.0, 1400.0)  # 30 px: all of it seen
        region = np.zeros(grey.shape, bool)
        x0, y0, x1, y1 = (int(round(c)) for c in roi_box(box, rule))
        region[y0:y1, x0:x1] = True
        mm_per_px = 1400.0**2 / (350.0 * 120.0)
        assert distance == pytest.approx(ev.floor_px(grey, region, 2.0) * mm_per_px, rel=1e-9)
        ring = ring_mask(grey.shape, box, rule.ring_gap_px, rule.ring_width_px)
        assert deviation == pytest.approx(math.hypot(distance, ev.floor_px(grey, ring, 2.0) * mm_per_px), rel=1e-9)
        texture = ev.defect_floors_mm(grey, box, calib, rule, 2.0, 1400.0, texture_only=True)
        assert texture[1] == pytest.approx(ev.floor_px(grey, region, 2.0, texture_only=True) * mm_per_px, rel=1e-9)
        assert texture[0] > deviation and texture[1] > distance

    def test_pixels_the_right_camera_does_not_see_are_left_out_of_the_floor(self):
        rng = np.random.default_rng(1)
        grey = rng.normal(100, 10, (120, 160)).astype(np.float32)
        calib = Calibration(focal_px=350.0, baseline_mm=120.0, cx=80.0, cy=60.0, width=160, height=120)
        box, rule = (60.0, 40.0, 100.0, 80.0), DepthRule()
        # at 700 mm the disparity is 60 px: the ring's left side (45-57) lies where the right camera does not look
        deviation, distance = ev.defect_floors_mm(grey, box, calib, rule, 2.0, 700.0)
        mm_per_px = 700.0**2 / (350.0 * 120.0)
        seen = np.arange(160) >= 60
        ring = ring_mask(grey.shape, box, rule.ring_gap_px, rule.ring_width_px)
        region = np.zeros(grey.shape, bool)
        x0, y0, x1, y1 = (int(round(c)) for c in roi_box(box, rule))
        region[y0:y1, x0:x1] = True
        assert distance == pytest.approx(ev.floor_px(grey, region, 2.0) * mm_per_px, rel=1e-9)  # all of it seen
        assert deviation == pytest.approx(math.hypot(distance, ev.floor_px(grey, ring & seen, 2.0) * mm_per_px),
                                          rel=1e-9)
        assert deviation > math.hypot(distance, ev.floor_px(grey, ring, 2.0) * mm_per_px)
        # at 350 mm (120 px) none of it: no floor (the report's None)
        assert ev.defect_floors_mm(grey, box, calib, rule, 2.0, 350.0) == (math.inf, math.inf)


class TestMixtureQuantile:
    def test_one_sigma_gives_the_half_normal_quantiles(self):
        assert ev.mixture_quantile(np.full(5, 2.0), 0.5) == pytest.approx(2.0 * 0.6745, rel=1e-3)
        assert ev.mixture_quantile(np.full(5, 2.0), 0.9) == pytest.approx(2.0 * 1.6449, rel=1e-3)

    def test_a_mixture_lies_between_its_parts(self):
        q = ev.mixture_quantile(np.array([1.0, 3.0]), 0.5)
        assert 0.6745 < q < 3 * 0.6745


class TestSummarise:
    def _row(self, true, measured, sigma, proven, true_status, clear_cut=True, floor=0.05):
        plain = "REJECT" if measured > 1.0 else "PASS"
        return ev.DefectRow("s", "000000", "pit", (0, 0, 40, 40), 400.0, true, floor, "surface", 400.0, measured, 0.1,
                            sigma, 400.0, measured, "", true_status, proven, proven, proven, proven, plain, plain,
                            clear_cut)

    def test_wrong_sides_count_only_proven_outcomes_of_clear_cut_defects(self):
        rows = [
            self._row(1.5, 1.45, 0.05, "REJECT", "REJECT"),
            self._row(1.5, 0.6, 0.05, "PASS", "REJECT"),  # a silent pass, far beyond 2 sigma
            self._row(1.5, 1.1, 0.1, "undecided", "REJECT"),  # the recipe's uncertain choice decides: no fault
            self._row(1.1, 0.7, 0.05, "PASS", "REJECT", clear_cut=False),  # near the limit: not clear-cut
        ]
        s = ev.summarise(rows)
        assert (s.clear_cut_wrong, s.clear_cut_silent_pass, s.clear_cut_wrong_beyond_2_sigma) == (1, 1, 1)
        assert s.clear_cut_wrong_plain == 1  # the undecided 1.1 mm counts as out on its value: right side
        assert s.confusion == {"REJECT": {"REJECT": 1, "PASS": 2, "undecided": 1}}
        assert s.within_2_sigma == pytest.approx(0.25)  # only the first error is within 2 sigma
        assert s.distance_within_2_sigma == 1.0  # each distance exact
        assert s.ratio_median == pytest.approx(np.median([1.45 / 1.5, 0.6 / 1.5, 1.1 / 1.5, 0.7 / 1.1]))

    def test_the_undecided_are_tallied_by_the_largest_part_of_their_uncertainty(self):
        rows = [dataclasses.replace(self._row(1.5, 1.1, 0.2, "undecided", "REJECT"), uncertainty_from="moved"),
                dataclasses.replace(self._row(0.8, 1.0, 0.2, "undecided", "PASS"), uncertainty_from="moved"),
                dataclasses.replace(self._row(0.8, 0.9, 0.2, "undecided", "PASS"), uncertainty_from="noise"),
                # proven outcomes, and a measurement without an account (the backend's map alone), are not tallied
                dataclasses.replace(self._row(1.5, 1.5, 0.05, "REJECT", "REJECT"), uncertainty_from="noise"),
                self._row(0.8, 0.9, 0.2, "undecided", "PASS")]
        assert ev.summarise(rows).undecided_from == {"moved": {"REJECT": 1, "PASS": 1}, "noise": {"PASS": 1}}
        assert ev.summarise(rows, reference=True).undecided_from == {}

    def test_the_distances_calibration_counts_its_errors_within_two_of_its_sigma(self):
        rows = [self._row(1.5, 1.5, 0.05, "REJECT", "REJECT") for _ in range(4)]
        for row, measured in zip(rows, (400.05, 399.85, 400.3, 399.0)):  # sigma 0.1 mm: 0.5, 1.5, 3 and 10 of it
            row.distance_mm = measured
        assert ev.summarise(rows).distance_within_2_sigma == pytest.approx(0.5)
        assert ev.summarise(rows, reference=True).distance_within_2_sigma is None  # the backend reports no sigma

    def test_the_error_per_defect_is_one_at_the_floor_whatever_the_mix_of_floors(self):
        rng = np.random.default_rng(0)
        floors = np.repeat([0.02, 0.5], 2000)  # a set whose median error follows its large floors
        rows = [self._row(1.5, 1.5 + e * f, 3 * f, "REJECT", "REJECT", floor=f)
                for f, e in zip(floors, rng.standard_normal(floors.size))]
        s = ev.summarise(rows)
        assert s.error_over_floor_per_defect == pytest.approx(1.0, abs=0.05)
        twice = ev.summarise([self._row(1.5, 1.5 + 2 * (r.deviation_mm - 1.5), 0.1, "REJECT", "REJECT", floor=r.floor_mm)
                              for r in rows])
        assert twice.error_over_floor_per_defect == pytest.approx(2.0, abs=0.1)

    def test_the_distance_per_defect_against_its_own_floor(self):
        rng = np.random.default_rng(2)
        rows = [self._row(1.5, 1.5, 0.1, "REJECT", "REJECT") for _ in range(2000)]
        for row, floor, e in zip(rows, np.repeat([0.05, 1.0], 1000), rng.standard_normal(2000)):
            row.distance_floor_mm, row.distance_mm = floor, 400.0 + 1.5 * floor * e
        assert ev.summarise(rows).distance_over_floor_per_defect == pytest.approx(1.5, abs=0.1)
        rows[0].distance_floor_mm = None  # a set without noise has none: that row does not count
        assert ev.summarise(rows[:1]).distance_over_floor_per_defect is None


class TestByClass:
    def _row(self, cls, true, measured, sigma, proven, true_status, width=20):
        row = TestSummarise()._row(true, measured, sigma, proven, true_status)
        return dataclasses.replace(row, cls=cls, box=(0, 0, width, width))

    def _body(self, rows):
        return ev.report(rows, {"recipe": "r.yaml", "backend": "b", "method": "surface", "machine": "m",
                                "uncertain": "reject"}, None)

    def test_each_class_is_summarised_from_its_own_defects(self):
        rows = [self._row("crazing", 2.0, 1.2, 0.2, "undecided", "REJECT"),  # a narrow one reading short
                self._row("crazing", 2.0, 1.9, 0.1, "REJECT", "REJECT", width=60),
                self._row("pit", 2.0, 2.0, 0.1, "REJECT", "REJECT"),
                self._row("pit", 0.5, 0.5, 0.1, "PASS", "PASS")]
        classes = self._body(rows)["classes"]
        assert list(classes) == ["crazing", "pit"]
        assert classes["crazing"]["defects"] == 2 and classes["crazing"]["narrow_ratio_median"] == pytest.approx(0.6)
        assert classes["crazing"]["ratio_median"] == pytest.approx(np.median([0.6, 0.95]))
        assert classes["pit"]["ratio_median"] == pytest.approx(1.0)
        assert classes["crazing"]["confusion"] == {"REJECT": {"undecided": 1, "REJECT": 1}}

    def test_the_table_gives_a_row_per_class_with_its_decisions(self):
        rows = [self._row("crazing", 2.0, 1.2, 0.2, "undecided", "REJECT"),
                self._row("crazing", 1.5, 0.5, 0.1, "PASS", "REJECT"),  # a clear-cut silent PASS
                self._row("pit", 0.5, 0.5, 0.1, "PASS", "PASS"),
                self._row("pit", 0.6, 0.8, 0.2, "undecided", "PASS")]
        table = ev.markdown(self._body(rows))
        assert "By the labels' class (surface; narrow: boxes under 30 px):" in table
        # the last three columns: inside the limit proven / undecided, beyond it the same, wrong side (silent PASS)
        ends = [line.split(" | ")[-3:] for line in table.splitlines() if line.startswith(("| crazing |", "| pit |"))]
        assert ends == [["0 / 0", "0 / 1", "1 (1) |"], ["1 / 1", "0 / 0", "0 (0) |"]]

    def test_one_class_alone_has_no_table_of_its_own(self):
        body = self._body([self._row("pit", 2.0, 2.0, 0.1, "REJECT", "REJECT")])
        assert list(body["classes"]) == ["pit"] and "By the labels' class" not in ev.markdown(body)


def test_a_plate_outside_the_working_distance_gets_no_deviation(tmp_path):
    """The demo recipe searches 350-500 mm; the first frame's plate lies at 634-645 mm. Whatever the matcher
    returns there, the images do not match at it, and no deviation is reported (the part is an ERROR, so
    rejected) instead of a confident wrong one."""
    copy = tmp_path / "seq"
    shutil.copytree(TEXTURED, copy)
    for folder in ("left", "right", "labels", "gt"):
        for f in (copy / folder).iterdir():
            if not f.stem.startswith("000000"):
                f.unlink()
    # from another folder: the demo recipe is found beside the package, not in the working folder
    result = cli("eval", "depth", str(copy), "--out", str(tmp_path / "out"), "--threads", "1", "--no-figure",
                 cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    rows = [r for r in json.loads((tmp_path / "out" / "depth_eval.json").read_text())["rows"] if r["method"] == "surface"]
    assert rows and all(r["true_distance_mm"] > 600 for r in rows)
    for r in rows:
        assert r["deviation_mm"] is None and r["status"] == "ERROR", r
        assert "do not match" in r["note"] or "did not settle" in r["note"]
    # without its defects the part would be an ERROR too: the images show its plate beyond 500 mm
    (flagged,) = json.loads((tmp_path / "out" / "depth_eval.json").read_text())["plate_check"]["flagged"]
    assert flagged["frame_id"] == "000000" and not flagged["swapped"] and flagged["distance_mm"] > 600
    assert "1 of 1 frames show the plate outside the working distance" in result.stdout


def test_a_set_rendered_without_noise_has_no_floor_to_compare_with(tmp_path):
    """``inspect sim generate --noise-sigma 0`` labels its frames with no noise: the errors are reported,
    the floor and the ratios to it are not (instead of a floor of zero and ratios of infinity)."""
    copy = tmp_path / "seq"
    shutil.copytree(TEXTURED, copy)
    for f in (copy / "labels").iterdir():
        labels = json.loads(f.read_text())
        labels["sensor"]["noise_sigma"] = 0.0
        f.write_text(json.dumps(labels))
    result = cli("eval", "depth", str(copy), "--set", RANGE, "--out", str(tmp_path / "out"), "--threads", "1",
                 "--no-figure")
    assert result.returncode == 0, result.stderr
    body = json.loads((tmp_path / "out" / "depth_eval.json").read_text())
    assert all(r["floor_mm"] is None for r in body["rows"])
    measured = body["all"]["measurement"]
    assert measured["deviation_error_mm"]["median"] > 0 and measured["floor_mm"] == {}
    assert measured["sigma_over_floor_median"] is None and measured["distance_over_floor_per_defect"] is None
    assert "nan" not in (tmp_path / "out" / "depth_eval.md").read_text()
