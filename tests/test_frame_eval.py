"""`inspect eval detector-frames`: the detector on whole labelled frames, as the line runs it."""
from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from core.cli import _build
from plugins.yolov8.frame_eval import markdown, score_frames
from sim.generate import generate_sequence


def test_score_frames_counts_found_defects_and_boxes_on_sound_surface():
    truths = [[{"class": "scratches", "box": [0, 0, 100, 20]}, {"class": "inclusion", "box": [200, 200, 220, 260]}],
              []]
    detections = [
        [("scratches", 0.9, (2, 0, 98, 22)),     # finds the scratch, right class
         ("patches", 0.45, (201, 205, 221, 255)),  # finds the inclusion, wrong class, low confidence
         ("pitted_surface", 0.6, (400, 10, 500, 90))],  # on sound surface
        [("pitted_surface", 0.35, (10, 10, 60, 60))],  # a frame without defects
    ]
    low, high = score_frames(detections, truths, [0.3, 0.5])
    assert (low.defects, low.found, low.found_same_class, low.other_boxes, low.frames) == (2, 2, 1, 2, 2)
    assert (high.found, high.found_same_class, high.other_boxes) == (1, 1, 1)
    assert high.other_per_frame == 0.5
    # each found defect's box against its own: the scratch's a pixel low on a 20 px height, the inclusion's a pixel
    # right on a 20 px width and shorter
    assert low.shifts == pytest.approx([0.05, 0.05]) and high.shifts == pytest.approx([0.05])
    assert low.scales == pytest.approx([np.sqrt(96 * 22 / 2000), np.sqrt(20 * 50 / 1200)])


def test_the_table_says_how_far_the_boxes_lie_off_their_defects():
    truths = [[{"class": "pitted_surface", "box": [0, 0, 30, 30]}, {"class": "inclusion", "box": [100, 0, 130, 30]},
               {"class": "crazing", "box": [200, 0, 230, 30]}]]
    detections = [[("pitted_surface", 0.9, (1, 0, 31, 30)),  # a thirtieth off
                   ("inclusion", 0.9, (106, 0, 136, 30)),  # a fifth off
                   ("crazing", 0.4, (212, 0, 242, 30))]]  # two fifths off, found only at the lower threshold
    table = markdown(score_frames(detections, truths, [0.3, 0.5]))
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[6:9]] for line in table.splitlines()
            if line.startswith("| 0.")}
    assert rows["0.30"] == ["0.20 / 0.40", "1.00-1.00", "2 (1) of 3"]
    assert rows["0.50"] == ["0.12 / 0.20", "1.00-1.00", "1 (0) of 2"]
    assert markdown(score_frames([[]], truths, [0.3])).splitlines()[2].endswith("| - | - | - |")


def test_cli_on_a_rendered_sequence(tmp_path, monkeypatch):
    seq = tmp_path / "plates"
    labels = generate_sequence(seq, frames=2, seed=5, width=448, height=300, neu_det=None)
    defects = sum(len(label["defects"]) for label in labels)
    runner = CliRunner()
    result = runner.invoke(_build(), ["eval", "detector-frames", str(seq), "--confidence", "0.5,0.25"])
    assert result.exit_code == 0, result.output
    rows = [line.split("|")[1:-1] for line in result.output.splitlines() if line.startswith("| 0.")]
    assert [r[0].strip() for r in rows] == ["0.25", "0.50"]
    found = [int(r[1].split("/")[0]) for r in rows]
    assert all(r[1].strip().endswith(f"/{defects}") for r in rows) and found[0] >= found[1]
    assert int(rows[0][3]) >= int(rows[1][3])  # a higher threshold never adds boxes
    # the network sees each image at its own scale: a 224 px tile at 224, the whole 448 px frame at 448
    from plugins.yolov8 import detector as yolo

    sizes = []
    original = yolo.YoloDetector._predict

    def recording(self, images, imgsz):
        sizes.append((images[0].shape[1], imgsz))
        return original(self, images, imgsz)

    monkeypatch.setattr(yolo.YoloDetector, "_predict", recording)
    for tile in ("224", "0"):
        result = runner.invoke(_build(), ["eval", "detector-frames", str(seq), "--tile-size", tile, "--confidence", "0.5"])
        assert result.exit_code == 0 and "| 0.50 |" in result.output, result.output
    assert set(sizes) == {(224, 224), (448, 448)}
    (seq / "labels" / "000001.json").write_text(json.dumps({"frame_id": "000001"}))
    broken = runner.invoke(_build(), ["eval", "detector-frames", str(seq)])
    assert broken.exit_code == 2 and "000001.json: expected a mapping with a list of defects" in broken.output
    (seq / "labels" / "000001.json").write_text(json.dumps({"frame_id": "000001", "defects": [
        {"class": "crazing", "box": [1, 2, 3]}]}))
    broken = runner.invoke(_build(), ["eval", "detector-frames", str(seq)])
    assert broken.exit_code == 2 and "000001.json: defects[0].box: expected [x0, y0, x1, y1]" in broken.output
    # a labelled defect where the frame has no pixels would count as one the detector missed
    (seq / "labels" / "000001.json").write_text(json.dumps({"frame_id": "000001", "defects": [
        {"class": "crazing", "box": [460, 2, 480, 30]}]}))
    broken = runner.invoke(_build(), ["eval", "detector-frames", str(seq)])
    assert broken.exit_code == 2 and "000001.json: defects[0].box: [460.0, 2.0, 480.0, 30.0] lies outside the " \
                                     "448x300 image" in broken.output, broken.output
    # a left image cut short decoded as the frame padded with grey: its defects there counted as missed
    (seq / "labels" / "000001.json").write_text(json.dumps({"frame_id": "000001", "defects": []}))
    left = sorted((seq / "left").glob("000001.*"))[0]
    left.write_bytes(left.read_bytes()[:5000])
    broken = runner.invoke(_build(), ["eval", "detector-frames", str(seq)])
    assert broken.exit_code == 2 and f"{left}: left image of frame 000001 is not whole: truncated" in broken.output, \
        broken.output


@pytest.mark.parametrize("args, message", [
    (["--confidence", "1.5"], "each threshold is a number from 0 to 1"),
    (["--tile-size", "10"], "0 (the whole frame) or at least 32"),
    (["--tile-overlap", "0.95"], "0.95 is not in the range"),
    (["--imgsz", "8"], "8 is not in the range"),
])
def test_cli_options_out_of_range_are_one_line_errors(args, message):
    # they reached the detector's settings and ended in a traceback
    result = CliRunner().invoke(_build(), ["eval", "detector-frames", "sim_fixtures/steel_plate", *args])
    assert result.exit_code == 2 and message in result.output, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception


def test_a_threshold_so_low_that_boxes_would_go_uncounted_is_refused():
    # the network stops at max_det boxes: more boxes on sound surface than that would not be counted
    result = CliRunner().invoke(_build(), ["eval", "detector-frames", "sim_fixtures/steel_plate", "--confidence", "0",
                                           "--tile-size", "0"])
    assert result.exit_code == 2, result.output
    assert "at --confidence 0 the detector finds 300 boxes or more in one image, more than it reports" in result.output
