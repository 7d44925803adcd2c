"""``inspect sim generate``."""
from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from core.cli import _build
from drivers.sequence_folder import list_frames, read_calibration, read_disparity_png


def test_missing_neu_det_is_a_one_line_error(tmp_path):
    result = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "out"), "--neu-det", str(tmp_path / "nope")])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "nope" in lines[0]
    assert not (tmp_path / "out").exists()


def test_not_a_neu_det_folder_is_a_one_line_error(tmp_path):
    (tmp_path / "empty").mkdir()
    result = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "out"), "--neu-det", str(tmp_path / "empty")])
    assert result.exit_code == 2
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "val.txt" in lines[0]


def test_generate_with_synthetic_defects(tmp_path):
    out = tmp_path / "seq"
    result = CliRunner().invoke(_build(), [
        "sim", "generate", str(out), "--frames", "2", "--seed", "5", "--synthetic-defects",
        "--width", "160", "--height", "96", "--distance-mm", "420", "--tilt-deg", "3", "--no-jitter",
        "--image-format", "jpg",
    ])
    assert result.exit_code == 0, result.output
    calib = read_calibration(out)
    assert (calib["width"], calib["height"]) == (160, 96) and calib["camera"] == "ZED WVGA (synthetic)"
    frames = list_frames(out)
    assert [f.frame_id for f in frames] == ["000000", "000001"]
    assert all(f.left.suffix == ".jpg" and f.right.suffix == ".jpg" and f.gt.suffix == ".png" for f in frames)
    labels = json.loads(frames[0].labels.read_text())
    assert labels["distance_mm"] == 420.0 and labels["tilt_deg"] == 3.0


def test_captures_repeat_each_plate_with_noise_of_its_own_and_leave_the_first_capture_as_it_was(tmp_path):
    import cv2
    import numpy as np

    args = ["--seed", "5", "--synthetic-defects", "--width", "160", "--height", "96", "--no-jitter",
            "--depth-range-mm", "0.5", "2", "--defect-size-px", "10", "20"]
    once, thrice = tmp_path / "once", tmp_path / "thrice"
    assert CliRunner().invoke(_build(), ["sim", "generate", str(once), "--frames", "1", *args]).exit_code == 0
    result = CliRunner().invoke(_build(), ["sim", "generate", str(thrice), "--frames", "2", "--captures", "3", *args])
    assert result.exit_code == 0, result.output
    assert "wrote 6 frames" in result.output
    frames = list_frames(thrice)
    assert [f.frame_id for f in frames] == [f"{i:06d}" for i in range(6)]
    grey = [cv2.imread(str(f.left), cv2.IMREAD_GRAYSCALE).astype(int) for f in frames]
    labels = [json.loads(f.labels.read_text()) for f in frames]
    assert [lab["plate"] for lab in labels] == [0, 0, 0, 1, 1, 1]
    for plate in (0, 3):
        for k in (1, 2):
            # the same plate under the same light: only the sensor's noise differs (1.5-2 grey levels)
            assert 0.5 < np.abs(grey[plate + k] - grey[plate]).mean() < 4.0
            assert {**labels[plate + k], "frame_id": ""} == {**labels[plate], "frame_id": ""}
            assert cv2.imread(str(frames[plate + k].gt), -1).tobytes() == cv2.imread(str(frames[plate].gt), -1).tobytes()
    assert np.abs(grey[3] - grey[0]).mean() > 10  # another plate
    # the first capture draws what a sequence without captures draws
    assert (thrice / "left" / "000000.png").read_bytes() == (once / "left" / "000000.png").read_bytes()
    assert "plate" not in json.loads((once / "labels" / "000000.json").read_text())


def test_a_capture_drift_moves_each_captures_right_eye_further_and_keeps_the_truth(tmp_path):
    import cv2

    args = ["--frames", "1", "--seed", "5", "--synthetic-defects", "--width", "160", "--height", "96", "--no-jitter",
            "--depth-range-mm", "0.5", "2", "--defect-size-px", "10", "20", "--noise-sigma", "0", "--captures", "3"]
    still, drifting = tmp_path / "still", tmp_path / "drifting"
    assert CliRunner().invoke(_build(), ["sim", "generate", str(still), *args]).exit_code == 0
    result = CliRunner().invoke(_build(), ["sim", "generate", str(drifting), *args, "--capture-drift-px", "0.5"])
    assert result.exit_code == 0, result.output
    frames = list_frames(drifting)
    assert [json.loads(f.labels.read_text())["right_columns_px"] for f in frames] == [0.0, 0.5, 1.0]

    def right(folder, frame_id):
        return cv2.imread(str(folder / "right" / f"{frame_id}.png"), cv2.IMREAD_GRAYSCALE).astype(np.float64)

    def apart(frame_id, columns):  # the drifting capture against the still one moved that many columns right
        a, b = right(drifting, frame_id), right(still, frame_id)
        return np.abs(a[:, 8 + columns:-8] - b[:, 8:b.shape[1] - 8 - columns]).mean()

    assert apart("000000", 0) == 0.0  # the first capture as it was
    # two captures on, a pixel further right (but for the vignetting, which stays where it was, and the rounding)
    assert apart("000002", 1) < 0.5 < 5 < apart("000002", 0)
    assert apart("000001", 0) > 2 and apart("000001", 1) > 2  # half a pixel: between the two
    for frame_id in ("000000", "000001", "000002"):  # the scene's truth, whatever the camera does
        assert (drifting / "gt" / f"{frame_id}.png").read_bytes() == (still / "gt" / f"{frame_id}.png").read_bytes()
    refused = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "one"), "--capture-drift-px", "0.5"])
    assert refused.exit_code == 2 and "needs --captures 2 or more" in refused.output


def test_existing_sequence_needs_overwrite(tmp_path):
    out = tmp_path / "seq"
    args = ["sim", "generate", str(out), "--frames", "2", "--synthetic-defects", "--width", "160", "--height", "96"]
    assert CliRunner().invoke(_build(), args).exit_code == 0
    result = CliRunner().invoke(_build(), args[:3] + ["--frames", "1", "--synthetic-defects", "--width", "160",
                                                      "--height", "96", "--image-format", "jpg"])
    assert result.exit_code == 2 and result.output.startswith("error: ") and "--overwrite" in result.output
    result = CliRunner().invoke(_build(), args[:3] + ["--frames", "1", "--synthetic-defects", "--width", "160",
                                                      "--height", "96", "--image-format", "jpg", "--overwrite"])
    assert result.exit_code == 0, result.output
    frames = list_frames(out)
    assert [(f.frame_id, f.left.suffix) for f in frames] == [("000000", ".jpg")]
    assert sorted(p.name for p in (out / "labels").iterdir()) == ["000000.json"]


def test_a_recording_is_not_replaced_even_with_overwrite(tmp_path):
    # a camera's frames (no gt/) were deleted for a render of the same name: a recording nothing can make again
    out = tmp_path / "recorded"
    args = ["sim", "generate", str(out), "--frames", "1", "--synthetic-defects", "--width", "160", "--height", "96"]
    assert CliRunner().invoke(_build(), args).exit_code == 0
    for path in [*(out / "gt").iterdir(), *(out / "labels").iterdir()]:
        path.unlink()
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    result = CliRunner().invoke(_build(), args + ["--overwrite"])
    assert result.exit_code == 2 and result.output == (f"error: {out} holds frames without ground truth (gt/), a "
                                                       f"recording rather than a render: --overwrite replaces only "
                                                       f"rendered sequences; choose a new folder\n"), result.output
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_evaluation_set_options(tmp_path):
    out = tmp_path / "eval"
    result = CliRunner().invoke(_build(), [
        "sim", "generate", str(out), "--frames", "2", "--synthetic-defects", "--width", "224", "--height", "126",
        "--distance-range-mm", "380", "460", "--defect-size-px", "8", "16", "--depth-range-mm", "0.3", "2.5",
        "--texture-contrast", "0.3", "--supersample", "1", "--noise-sigma", "0.5", "--no-specular",
        "--lens-blur-px", "0.6", "--grain-angle-deg", "90", "--motion-blur-px", "2", "--motion-angle-deg", "0",
        "--baseline-mm", "63",
    ])
    assert result.exit_code == 0, result.output
    calib = read_calibration(out)
    assert calib["baseline_mm"] == 63.0 and calib["focal_px"] == pytest.approx(350.06 * 224 / 672)
    fb = calib["focal_px"] * 63.0
    for f in list_frames(out):  # the truth is the disparity of a 63 mm baseline at 380-460 mm
        disparity = read_disparity_png(f.gt)
        assert 0.9 * fb / 470 < np.nanmedian(disparity[disparity > 0]) < 1.1 * fb / 370
    for f in list_frames(out):
        labels = json.loads(f.labels.read_text())
        assert 380 <= labels["distance_mm"] <= 460 and labels["texture_contrast"] == 0.3 and labels["defects"]
        assert labels["sensor"]["noise_sigma"] == 0.5 and labels["specular"] is False and labels["lens_blur_px"] == 0.6
        assert labels["grain_angle_deg"] == 90.0 and (labels["motion_blur_px"], labels["motion_angle_deg"]) == (2.0, 0.0)


def test_a_reversed_range_is_a_one_line_error(tmp_path):
    result = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "x"), "--synthetic-defects",
                                           "--depth-range-mm", "2", "1"])
    assert result.exit_code == 2 and result.output.startswith("error: --depth-range-mm: MIN 2 is larger than MAX 1")
    assert not (tmp_path / "x").exists()


def test_a_negative_noise_is_refused(tmp_path):
    result = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "x"), "--synthetic-defects",
                                           "--noise-sigma", "-1"])
    assert result.exit_code == 2 and "--noise-sigma" in result.output
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("command", ["generate", "faults"])
def test_a_negative_seed_is_refused_not_a_traceback(tmp_path, command):
    result = CliRunner().invoke(_build(), ["sim", command, str(tmp_path / "x"), "--seed", "-1"])
    assert result.exit_code == 2 and "Invalid value for '--seed': -1 is not in the range x>=0" in result.output
    assert not (tmp_path / "x").exists()


def test_a_defect_larger_than_the_frame_holds_is_a_one_line_error(tmp_path):
    # it used to be left out of every frame without a word: an evaluation set with no defects
    result = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "x"), "--synthetic-defects",
                                           "--width", "224", "--height", "126", "--defect-size-px", "8", "90"])
    assert result.exit_code == 2 and result.output == (
        "error: --defect-size-px: a side of 90 px does not fit a 224x126 frame with room for the ring around it "
        "(below 82 px)\n")
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("args, says", [
    # each ran out of memory (a traceback) or rendered for minutes into tens of GB
    (["--distance-mm", "1e9"], "'--distance-mm': 1000000000.0 is not in the range 100.0<=x<=20000.0"),
    (["--distance-range-mm", "300", "1e6", "--depth-range-mm", "0.3", "2"],
     "--distance-range-mm: 1e+06 is beyond the largest allowed, 20000"),
    (["--width", "4096"], "'--width': 4096 is not in the range 32<=x<=2208"),
    (["--width", "2208", "--height", "1242", "--supersample", "3"],
     "--supersample 3 at 2208x1242 casts 25 M rays per eye, more than the 16 M"),
])
def test_a_scene_no_memory_holds_is_refused_before_rendering(tmp_path, args, says):
    result = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "x"), "--synthetic-defects", *args])
    assert result.exit_code == 2 and says in result.output, result.output
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("depths, says", [(("1e300", "1e301"), "1e+301 is beyond the largest allowed, 50"),
                                           (("-60", "1"), "-60 is below the smallest allowed, -50")])
def test_a_defect_deeper_than_a_plate_is_refused(tmp_path, depths, says):
    # 1e300 mm rendered a pit whose truth could not be measured, and the progress line ended in a TypeError
    result = CliRunner().invoke(_build(), ["sim", "generate", str(tmp_path / "x"), "--synthetic-defects",
                                           "--depth-range-mm", *depths])
    assert result.exit_code == 2 and result.output.startswith(f"error: --depth-range-mm: {says}"), result.output


def test_a_frame_that_cannot_be_written_is_a_one_line_error(tmp_path):
    out = tmp_path / "x"
    out.mkdir()
    (out / "left").write_text("a file where the left images go")
    result = CliRunner().invoke(_build(), ["sim", "generate", str(out), "--synthetic-defects", "--frames", "1",
                                           "--width", "224", "--height", "126", "--supersample", "1"])
    assert result.exit_code == 2 and result.output.startswith("error: ") and result.output.count("\n") == 1
    assert str(out / "left") in result.output and "Traceback" not in result.output
