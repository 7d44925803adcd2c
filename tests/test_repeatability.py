"""Repeatability (``core.repeatability``, ``inspect eval repeatability``): one part captured several times, held to
one verdict and to the uncertainty it is reported with."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import ROOT, cli, cli_here

from core.repeatability import (Capture, Defect, Labelled, Reading, Spread, Study, Trend, chi2_upper_ratio, same_defects,
                                t_quantile)
from core.types import Status

FIXTURE = ROOT / "sim_fixtures" / "steel_plate"
BOX = (100.0, 50.0, 140.0, 80.0)


def _reading(box=BOX, deviation=1.5, sigma=0.1, distance=420.0, distance_sigma=0.05, proof=Status.REJECT,
             cls="pitted_surface") -> Reading:
    return Reading(cls, tuple(box), deviation, sigma, distance, distance_sigma, proof)


def _captures(*per_capture: list[Reading], verdict=Status.REJECT) -> list[Capture]:
    return [Capture(f"{i:06d}", verdict, tuple(readings)) for i, readings in enumerate(per_capture)]


class TestChi2UpperRatio:
    @pytest.mark.parametrize("dof, quantile", [(2, 9.210), (4, 13.277), (9, 21.666), (29, 49.588), (99, 135.807)])
    def test_is_the_chi_squares_upper_99_percent_point_over_its_degrees_of_freedom(self, dof, quantile):
        assert chi2_upper_ratio(dof) == pytest.approx(quantile / dof, rel=0.02)

    def test_falls_towards_one_with_more_degrees_of_freedom(self):
        ratios = [chi2_upper_ratio(k) for k in (2, 5, 10, 50, 500)]
        assert ratios == sorted(ratios, reverse=True) and 1.0 < ratios[-1] < 1.2


class TestSpread:
    def test_needs_two_measured_values(self):
        assert Spread.of([1.0], [0.1]) is None
        assert Spread.of([1.0, None, 2.0], [0.1, 0.1, None]) is None  # a value without its sigma is not one

    def test_mean_scatter_and_the_reported_sigmas_root_mean_square(self):
        spread = Spread.of([1.0, 2.0, 3.0], [0.3, 0.4, 0.5])
        assert (spread.n, spread.mean, spread.sd) == (3, 2.0, 1.0)
        assert spread.sigma == pytest.approx(np.sqrt((0.09 + 0.16 + 0.25) / 3))
        assert spread.ratio == pytest.approx(1.0 / spread.sigma)

    def test_an_honest_uncertainty_is_contradicted_about_once_in_a_hundred(self):
        rng = np.random.default_rng(0)
        draws = [Spread.of(list(rng.normal(0.0, 0.2, 10)), [0.2] * 10).contradicts for _ in range(4000)]
        assert 0.003 < np.mean(draws) < 0.02

    def test_a_scatter_three_times_the_uncertainty_contradicts_it(self):
        rng = np.random.default_rng(1)
        draws = [Spread.of(list(rng.normal(0.0, 0.6, 10)), [0.2] * 10).contradicts for _ in range(1000)]
        assert np.mean(draws) > 0.95

    def test_a_scatter_below_the_uncertainty_does_not(self):
        # the uncertainty holds more than the noise: the wall, an uneven floor, a box that may be off
        assert not Spread.of([1.00, 1.02, 0.98, 1.01], [0.3] * 4).contradicts

    def test_two_values_say_nothing_of_a_scatter(self):
        assert not Spread.of([0.0, 5.0], [0.1, 0.1]).contradicts


class TestTQuantile:
    @pytest.mark.parametrize("dof, quantile, within", [(3, 5.841, 0.035), (5, 4.032, 0.006), (8, 3.355, 0.002),
                                                       (18, 2.878, 0.001)])
    def test_is_students_two_sided_99_percent_point(self, dof, quantile, within):
        assert t_quantile(dof) == pytest.approx(quantile, rel=within)


class TestTrend:
    def test_needs_three_measured_values(self):
        assert Trend.of([0, 1, 2], [1.0, None, 2.0]) is None

    def test_a_straight_line_is_its_change_from_the_first_capture_to_the_last(self):
        trend = Trend.of([0, 1, 2, 3, 4], [420.0, 420.1, 420.2, 420.3, 420.4])
        assert trend.change == pytest.approx(0.4) and trend.se == pytest.approx(0.0, abs=1e-9) and trend.drifts

    def test_a_capture_that_did_not_measure_keeps_the_others_in_their_places(self):
        # the third capture missed the defect: the others still lie 0.1 mm a capture apart
        assert Trend.of([0, 1, 3, 4, 5], [0.0, 0.1, 0.3, 0.4, 0.5]).change == pytest.approx(0.5)

    def test_noise_alone_drifts_about_once_in_a_hundred(self):
        rng = np.random.default_rng(3)
        draws = [Trend.of(list(range(10)), list(rng.normal(0.0, 0.2, 10))).drifts for _ in range(4000)]
        assert 0.003 < np.mean(draws) < 0.02

    def test_a_drift_of_five_times_the_scatter_is_found(self):
        rng = np.random.default_rng(4)
        draws = [Trend.of(list(range(10)), list(np.linspace(0.0, 1.0, 10) + rng.normal(0.0, 0.2, 10))).drifts
                 for _ in range(1000)]
        assert np.mean(draws) > 0.9

    def test_four_captures_say_nothing_of_a_drift(self):
        assert not Trend.of([0, 1, 2, 3], [0.0, 0.1, 0.2, 0.31]).drifts


class TestSameDefects:
    def test_readings_that_overlap_are_one_defect_in_the_order_first_found(self):
        other = (300.0, 200.0, 330.0, 240.0)
        moved = (102.0, 51.0, 141.0, 82.0)
        defects = same_defects(_captures([_reading()], [_reading(moved), _reading(other)], [_reading(other)]))
        assert [d.box for d in defects] == [BOX, other]
        assert [d.found for d in defects] == [2, 2] and all(d.captures == 3 for d in defects)
        assert [f for f, _ in defects[0].readings] == ["000000", "000001"]

    def test_two_readings_of_one_capture_are_two_defects(self):
        near = (104.0, 52.0, 142.0, 80.0)
        defects = same_defects(_captures([_reading(), _reading(near)]))
        assert len(defects) == 2 and [d.found for d in defects] == [1, 1]

    def test_a_box_overlapping_less_than_half_is_another_defect(self):
        half_off = (120.0, 50.0, 160.0, 80.0)  # IoU 1/3
        assert len(same_defects(_captures([_reading()], [_reading(half_off)]))) == 2

    def test_labelled_defects_come_first_and_count_however_seldom_found(self):
        labelled = (Labelled("crazing", (10.0, 10.0, 30.0, 30.0), 0.4), Labelled("pitted_surface", BOX, 1.6))
        defects = same_defects(_captures([_reading()], [_reading()]), labelled)
        assert [(d.label, d.found, d.reference_mm) for d in defects] == [("crazing", 0, 0.4), ("pitted_surface", 2, 1.6)]
        assert defects[0].name() == "crazing at (10, 10)-(30, 30) (labelled)"


class TestDefectFindings:
    def _defect(self, readings, captures=None, label=None) -> Defect:
        return Defect(BOX, tuple((f"{i:06d}", r) for i, r in enumerate(readings)), captures or len(readings), label)

    def test_none_for_a_defect_read_alike_within_its_uncertainty(self):
        assert self._defect([_reading(deviation=1.5 + d) for d in (0.01, -0.02, 0.0, 0.02)]).findings() == []

    def test_found_only_sometimes(self):
        (said,) = self._defect([_reading()] * 3, captures=5).findings()
        assert said == "pitted_surface at (100, 50)-(140, 80): found in 3 of 5 captures"

    def test_proven_on_both_sides_of_a_limit(self):
        readings = [_reading(proof=Status.REJECT), _reading(proof=Status.PASS), _reading(proof=Status.FLAG)]
        (said,) = self._defect(readings).findings()
        assert "proven beyond its limit in 1 captures and inside it in 1" in said

    def test_undecided_and_proven_on_one_side_is_no_contradiction(self):
        assert self._defect([_reading(proof=Status.REJECT), _reading(proof=Status.FLAG)] * 2).findings() == []

    def test_a_deviation_scattering_beyond_its_uncertainty(self):
        (said,) = self._defect([_reading(deviation=d, sigma=0.05) for d in (1.0, 1.5, 2.0, 1.2)]).findings()
        assert said.startswith("pitted_surface at (100, 50)-(140, 80): its deviation scatters 0.435 mm over 4 captures")
        assert "the box" not in said  # it did not move

    def test_a_distance_scattering_where_the_box_moved_says_so(self):
        readings = [_reading(box=(100.0 + dx, 50.0, 140.0 + dx, 80.0), distance=420.0 + 0.3 * dx) for dx in (0, 2, 4, 6)]
        (said,) = self._defect(readings).findings()
        assert "its distance scatters" in said and "the box's centre moved 2.6 px between captures" in said

    def test_a_distance_drifting_over_the_captures(self):
        readings = [_reading(distance=420.0 + 0.04 * k + d) for k, d in enumerate((0.0, 0.01, -0.01, 0.0, 0.01, -0.01))]
        (said,) = self._defect(readings).findings()  # its scatter, 0.075 mm, is within the 0.05 mm uncertainty's 99 %
        assert said.startswith("pitted_surface at (100, 50)-(140, 80): its distance drifts +0.194 mm from the first "
                               "capture to the last, more than its 0.050 mm uncertainty (6 captures in the order taken,")
        assert "the camera warming up" in said

    def test_a_drift_within_the_reported_uncertainty_is_no_finding(self):
        readings = [_reading(distance=420.0 + 0.04 * k + d, distance_sigma=0.25)
                    for k, d in enumerate((0.0, 0.01, -0.01, 0.0, 0.01, -0.01))]
        assert self._defect(readings).trend("distance").drifts  # sure, but 0.19 mm within a 0.25 mm uncertainty
        assert self._defect(readings).findings() == []

    def test_the_drift_is_taken_over_the_captures_in_the_order_taken(self):
        # found in captures 0, 1, 2 and 7, 8, 9 of ten, on a straight line over the ten
        places = (0, 1, 2, 7, 8, 9)
        readings = [_reading(distance=420.0 + 0.02 * k) for k in places]
        taken = tuple(f"{i:06d}" for i in range(10))
        trend = Defect(BOX, tuple(zip([taken[i] for i in places], readings)), 10, None, None, taken).trend("distance")
        assert trend.change == pytest.approx(0.18) and trend.se == pytest.approx(0.0, abs=1e-9)
        assert self._defect(readings).trend("distance").se > 0.01  # read one after another, no line

    def test_box_scatter_is_none_for_one_reading(self):
        assert self._defect([_reading()]).box_scatter_px is None


class TestStudy:
    def test_alike_every_time(self):
        study = Study("part", tuple(_captures([_reading()], [_reading(deviation=1.52)], [_reading(deviation=1.49)])))
        assert study.findings() == []
        assert study.summary() == ("part: 3 captures, REJECT 3; 1 defects; inspected alike every time, every scatter "
                                   "within its uncertainty")

    def test_a_verdict_that_differs_and_a_capture_that_could_not_be_inspected(self):
        captures = [*_captures([_reading()], [_reading()]), Capture("000002", Status.ERROR, (), "frame 000002: no image")]
        found = Study("part", tuple(captures)).findings()
        assert found[0] == "the part's verdict differs between captures (REJECT 2, ERROR 1)"
        assert found[1] == "capture 000002 could not be inspected: frame 000002: no image"
        assert found[2].endswith("found in 2 of 3 captures")

    def test_the_table_and_the_json_give_each_defect_against_its_labels(self):
        labelled = (Labelled("pitted_surface", BOX, 1.45),)
        study = Study("part", tuple(_captures([_reading()], [_reading(deviation=1.52)], [_reading(deviation=1.49)])),
                      labelled)
        (row,) = study.to_json()["defects"]
        assert row["found"] == 3 and row["proofs"] == {"beyond": 3}
        assert row["deviation_mm"]["mean"] == pytest.approx(1.5033, abs=1e-4)
        assert row["bias_mm"] == pytest.approx(0.0533, abs=1e-4) and row["reference_mm"] == 1.45
        table = study.markdown().splitlines()
        assert table[-1].startswith("| pitted_surface at (100, 50)-(140, 80) (labelled) | 3 of 3 | 0.0 | +1.503 | 0.015 |")
        assert "| +1.450 | +0.053 |" in table[-1] and table[-1].endswith("| beyond 3 |")

    def test_a_part_without_defects(self):
        study = Study("part", tuple(_captures([], [], verdict=Status.PASS)))
        assert study.findings() == [] and "no defect labelled or found" in study.markdown()


def _captures_of(frame_id: str, out: Path, count: int, noise: float = 1.5, seed: int = 0, drift_px: float = 0.0
                 ) -> Path:
    """``count`` captures of one demo frame: its images with the sensor's noise drawn anew each time; ``drift_px``
    moves the right image that much further right each capture (a camera whose rectification drifts as it warms)."""
    rng = np.random.default_rng(seed)
    for sub in ("left", "right", "labels"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    shutil.copy(FIXTURE / "calib.yaml", out)
    labels = json.loads((FIXTURE / "labels" / f"{frame_id}.json").read_text())
    for k in range(count):
        for eye in ("left", "right"):
            image = cv2.imread(str(FIXTURE / eye / f"{frame_id}.jpg")).astype(np.float32)
            if eye == "right" and drift_px:
                move = np.float32([[1, 0, drift_px * k], [0, 1, 0]])
                image = cv2.warpAffine(image, move, image.shape[1::-1], flags=cv2.INTER_CUBIC,
                                       borderMode=cv2.BORDER_REPLICATE)
            noisy = image + rng.normal(0.0, noise, image.shape[:2])[..., None]
            cv2.imwrite(str(out / eye / f"{k:06d}.png"), np.clip(np.round(noisy), 0, 255).astype(np.uint8))
        (out / "labels" / f"{k:06d}.json").write_text(json.dumps({**labels, "frame_id": f"{k:06d}"}))
    return out


def test_parts_in_their_labelled_boxes_are_inspected_alike_and_within_their_uncertainty(tmp_path):
    part = _captures_of("000003", tmp_path / "part", 5)
    warming = _captures_of("000003", tmp_path / "warming", 5, seed=2, drift_px=0.05)
    broken = _captures_of("000006", tmp_path / "broken", 3, seed=1)
    (broken / "right" / "000001.png").write_bytes(b"not an image")
    plates = tmp_path / "plates"  # two rendered plates, each captured twice: a study of each
    made = cli_here("sim", "generate", str(plates), "--frames", "2", "--captures", "2", "--seed", "5",
                    "--synthetic-defects", "--no-jitter", "--width", "336", "--height", "188", "--depth-range-mm",
                    "0.5", "2", "--defect-size-px", "20", "40", "--defects-per-frame", "1", "1")
    assert made.returncode == 0, made.stderr
    out = cli("eval", "repeatability", str(part), str(broken), str(warming), str(plates), "--boxes", "labels",
              "--out", str(tmp_path / "out"))
    assert out.returncode == 1, out.stderr  # the broken part's capture, the warming camera's drift
    result = json.loads((tmp_path / "out" / "repeatability.json").read_text())
    first, second, third, *rendered = result["parts"]
    assert [(p["part"], p["captures"]) for p in rendered] == [
        (f"{plates} plate 0", ["000000", "000001"]), (f"{plates} plate 1", ["000002", "000003"])]
    for study, capture in zip(rendered, ("000000", "000002")):
        labels = json.loads((plates / "labels" / f"{capture}.json").read_text())["defects"]
        assert [row["box"] for row in study["defects"]] == [d["box"] for d in labels]
        assert all(row["found"] == 2 for row in study["defects"])
    assert first["verdicts"] == {"REJECT": 5} and first["findings"] == []
    for row in first["defects"]:
        assert row["found"] == 5 and row["box_scatter_px"] == 0.0  # the labels' boxes hold still
        dev = row["deviation_mm"]
        assert dev["n"] == 5 and 0 < dev["sd"] < dev["sigma"]
        assert abs(row["bias_mm"]) < 2 * dev["sigma"]
        assert not row["distance_trend_mm"]["drifts"] and not row["deviation_trend_mm"]["drifts"]
    assert f"{part}: 5 captures, REJECT 5; 2 defects; inspected alike every time" in out.stdout
    # 0.2 px of disparity over the five captures: the plate some 0.8 mm farther at the last, the deviations as they were
    for row, steady in zip(third["defects"], first["defects"]):
        trend = row["distance_trend_mm"]
        assert trend["drifts"] and 0.5 < trend["change"] < 1.2, trend
        assert abs(row["deviation_mm"]["mean"] - steady["deviation_mm"]["mean"]) < 2 * steady["deviation_mm"]["sigma"]
        assert any("its distance drifts +" in f for f in row["findings"])
    assert second["verdicts"]["ERROR"] == 1
    assert any(f.startswith("capture 000001 could not be inspected") for f in second["findings"])
    assert f"  {broken}: capture 000001 could not be inspected" in out.stdout
    assert (tmp_path / "out" / "repeatability.md").read_text().startswith(f"### {part}")


def test_folders_that_cannot_make_a_study_are_refused_before_the_model_loads(tmp_path, monkeypatch):
    import core.engine

    def no_model(*args, **kwargs):
        raise AssertionError("the detector was built before the folders were checked")

    monkeypatch.setattr(core.engine, "build_detector", no_model)
    good = _captures_of("000003", tmp_path / "good", 2)
    twice = _captures_of("000003", tmp_path / "twice", 2)
    for eye in ("left", "right"):
        shutil.copy(twice / eye / "000000.png", twice / eye / "000001.png")
    once = _captures_of("000003", tmp_path / "once", 1)
    lone = _captures_of("000003", tmp_path / "lone", 3, seed=4)  # a third capture of another plate
    (lone / "labels" / "000002.json").write_text(json.dumps({"frame_id": "000002", "plate": 7, "defects": []}))
    unlabelled = _captures_of("000003", tmp_path / "unlabelled", 2, seed=2)
    (unlabelled / "labels" / "000001.json").unlink()
    broken = _captures_of("000003", tmp_path / "broken", 2, seed=3)
    (broken / "labels" / "000000.json").write_text("{")
    for folder, boxes, said in (
            (twice, "detector", f"{twice}: frames 000000 and 000001 hold the same images: a camera that delivered its "
                                f"last frame again, or a copied file; a repeatability study needs captures of their own"),
            (once, "detector", f"{once}: 1 capture; a repeatability study needs two or more of the same part"),
            (lone, "detector", f"{lone}: 1 capture of plate 7; a repeatability study needs two or more of the same "
                               f"part"),
            (unlabelled, "labels", f"{unlabelled}: frame 000001 has no labels/000001.json (--boxes labels measures in "
                                   f"its labelled boxes)"),
            (broken, "detector", f"{broken / 'labels' / '000000.json'}: labels are not JSON"),
            (good, "detector", f"{good}: given twice (also as {good})")):
        parts = (str(good), str(folder))
        out = cli_here("eval", "repeatability", *parts, "--boxes", boxes, "--out", str(tmp_path / "out"))
        assert out.returncode == 2, out.stdout
        (line,) = out.stderr.strip().splitlines()
        assert line.startswith(f"error: {said}")
    assert not (tmp_path / "out" / "repeatability.json").exists()
