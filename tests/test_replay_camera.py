from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest
import yaml
from conftest import png_declaring

from core.contracts import PluginContext
from core.registry import default_registry
from core.types import FrameError, StereoFrame
from drivers.sequence_folder import SequenceError, read_calibration, read_labels


def _camera(folder, **settings):
    spec = default_registry().get("camera", "replay").spec
    return spec.factory({"path": str(folder), **settings}, PluginContext())


def test_plays_every_frame_in_order_with_calibration(plane_sequence):
    info = plane_sequence([0.0, 1.0, 2.0])
    frames = list(_camera(info["folder"]).frames())
    assert [f.frame_id for f in frames] == ["000000", "000001", "000002"]
    assert all(isinstance(f, StereoFrame) for f in frames)
    assert frames[0].calib.focal_px == pytest.approx(350.06) and frames[0].calib.baseline_mm == 120.0
    assert frames[0].left.shape == (192, 320, 3) and "gt_disparity" in frames[0].meta


def test_loop_and_max_frames(plane_sequence):
    info = plane_sequence([0.0, 1.0])
    frames = list(_camera(info["folder"], loop=True, max_frames=5).frames())
    assert [f.index for f in frames] == [0, 1, 2, 3, 4]
    assert [f.frame_id for f in frames] == ["000000", "000001"] * 2 + ["000000"]
    assert frames[4].meta["pass"] == 2


def test_rate_is_kept(plane_sequence):
    info = plane_sequence([0.0, 0.0, 0.0, 0.0])
    start = time.monotonic()
    list(_camera(info["folder"], rate_fps=20).frames())
    assert time.monotonic() - start >= 3 / 20 * 0.9


@pytest.mark.parametrize("rate, says", [(1e-300, "1e-300: 0 (as fast as the line takes them) or at least 0.01 frames"),
                                         (5000, "less than or equal to 1000")])
def test_a_rate_no_replay_can_keep_is_refused(plane_sequence, rate, says):
    # at 1e-300 fps the wait for the second frame overflowed the clock, and the run stopped on it
    info = plane_sequence([0.0])
    with pytest.raises(ValueError, match=re.escape(says)):
        _camera(info["folder"], rate_fps=rate)


def test_corrupt_and_missing_frames_are_errors_not_skips(plane_sequence):
    info = plane_sequence([0.0, 0.0, 0.0])
    folder = info["folder"]
    (folder / "right" / "000001.png").write_bytes(b"\x89PNG not really")
    (folder / "left" / "000002.png").unlink()
    frames = list(_camera(folder).frames())
    assert [type(f) for f in frames] == [StereoFrame, FrameError, FrameError]
    assert "000001.png" in frames[1].message and "not whole" in frames[1].message
    assert "left image of frame 000002 missing" in frames[2].message


@pytest.mark.parametrize("name, data, says", [
    ("a.png", b"hello", "not a PNG (no PNG signature)"),
    ("a.png", b"\x89PNG\r\n\x1a\n cut", "truncated PNG (no IEND chunk at its end)"),
    ("a.jpg", b"GIF89a", "not a JPEG (no start-of-image marker)"),
    ("a.JPEG", b"\xff\xd8 cut", "truncated JPEG (no end-of-image marker)"),
    ("a.jpg", b"\xff\xd8 whole \xff\xd9\x00\x00", None),
])
def test_why_an_encoded_image_is_not_whole(name, data, says):
    """``sequence_folder.incomplete``: a file that is no such image is told from one cut short."""
    from drivers.sequence_folder import incomplete

    assert incomplete(data, Path(name).suffix) == says


def test_an_image_declaring_more_pixels_than_any_camera_is_refused_before_decoding(plane_sequence):
    # 10000 x 7000 in 70 KB: decoded, 210 MB before its size could be held against the calibration's
    # (a later frame: the camera's opening holds the first one's size against the calibration)
    info = plane_sequence([0.0, 0.0])
    (info["folder"] / "left" / "000001.png").write_bytes(png_declaring(10_000, 7_000))
    first, frame = list(_camera(info["folder"]).frames())
    assert isinstance(frame, FrameError) and not isinstance(first, FrameError)
    assert "left image of frame 000001 declares more than 64 MP, more than any camera's frame" in frame.message


def test_a_recording_of_another_size_than_its_calibration_is_refused_when_the_camera_opens(plane_sequence):
    # each part had become an ERROR and the run an alarm, once the line ran; `inspect validate` said nothing
    import cv2

    info = plane_sequence([0.0, 0.0])
    for eye in ("left", "right"):
        for path in (info["folder"] / eye).glob("*.png"):
            cv2.imwrite(str(path), cv2.resize(cv2.imread(str(path)), (160, 120)))
    with pytest.raises(ValueError, match=re.escape("left/000000.png is 160x120 but the calibration is for 320x192 "
                                                   "images: the calibration file is not this recording's")):
        _camera(info["folder"])


def test_a_damaged_tiff_is_refused_without_pillows_warnings(plane_sequence, recwarn):
    # reading its declared size printed Pillow's "Corrupt EXIF data" and "Truncated File Read" warnings on
    # the line's console, beside the part's own ERROR
    import cv2

    info = plane_sequence([0.0])
    image = cv2.imread(str(info["folder"] / "left" / "000000.png"))
    (info["folder"] / "left" / "000000.png").unlink()
    ok, data = cv2.imencode(".tif", image)
    (info["folder"] / "left" / "000000.tif").write_bytes(data.tobytes()[: len(data) // 2])
    (frame,) = list(_camera(info["folder"]).frames())
    assert isinstance(frame, FrameError) and "000000.tif: left image of frame 000000 cannot be decoded" in frame.message
    assert [str(w.message) for w in recwarn] == []


def test_a_frame_with_two_images_in_one_eye_is_refused_naming_both(plane_sequence):
    # which of them was the part is not the reader's guess to make (it took the later name silently)
    info = plane_sequence([0.0, 0.0])
    folder = info["folder"]
    (folder / "left" / "000001.jpg").write_bytes((folder / "left" / "000001.png").read_bytes())
    with pytest.raises(SequenceError, match=r"left: two images for frame 000001 \(000001.jpg and 000001.png\): keep one"):
        _camera(folder)


def test_missing_calibration(plane_sequence):
    info = plane_sequence([0.0])
    (info["folder"] / "calib.yaml").unlink()
    with pytest.raises(ValueError, match="calib.yaml: calibration file missing"):  # the settings' check says it
        _camera(info["folder"])


def _calibration_changed(plane_sequence, change):
    """A one-frame sequence's folder whose calib.yaml ``change`` (a function of its mapping) has rewritten."""
    info = plane_sequence([0.0])
    path = info["folder"] / "calib.yaml"
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data))
    return info["folder"]


class TestReadCalibration:
    """``sequence_folder.read_calibration``: a camera's values, or one line naming the file and the key."""

    @pytest.mark.parametrize("key, value, says", [
        ("focal_px", -350.0, "focal_px must be positive (got -350.0)"),
        ("baseline_mm", 0.0, "baseline_mm must be positive"),
        ("width", 672.5, "width must be a whole number of pixels above 0 (got 672.5)"),
        ("height", 0, "height must be a whole number"),
        ("cx", "centre", "cx must be a number (got 'centre')"),
        ("doffs", float("nan"), "doffs must be a number"),
        ("doffs", 1000.0, "doffs must lie within the image's width, 320 px (got 1000.0)"),
        # a principal point far off made every deviation about 0 mm: every defective plate passed
        ("cx", 1e30, "cx 1e+30 lies far outside the 320 px wide image"),
        ("baseline_mm", 0.12, "baseline_mm 0.12 lies outside 1-10000 mm (metres written for millimetres?)"),
        ("focal_px", 1e300, "focal_px 1e+300 is no camera's for a 320 px wide image"),
    ])
    def test_a_value_no_camera_has_is_named(self, plane_sequence, key, value, says):
        folder = _calibration_changed(plane_sequence, lambda data: data.update({key: value}))
        with pytest.raises(SequenceError, match=re.escape(f"calib.yaml: {says}")):
            read_calibration(folder)

    def test_a_key_given_twice_is_named_with_both_lines(self, plane_sequence):
        # YAML keeps the second focal length without a word: every depth of the sequence would follow it
        info = plane_sequence([0.0])
        path = info["folder"] / "calib.yaml"
        path.write_text(path.read_text() + "focal_px: 700.0\n")
        lines = path.read_text().splitlines()
        first = next(n for n, text in enumerate(lines, 1) if text.startswith("focal_px:"))
        with pytest.raises(SequenceError, match=re.escape(
                f"calib.yaml:{len(lines)}: focal_px: given twice (first at line {first}); one of them would be ignored")):
            read_calibration(info["folder"])

    @pytest.mark.parametrize("typo, meant", [("dofs", "doffs"), ("doffset", "doffs"), ("basline_mm", "baseline_mm"),
                                             ("focal", "focal_px")])
    def test_a_misspelt_key_is_named_with_the_key_it_reads_like(self, plane_sequence, typo, meant):
        # doffs has a default: "dofs: 40" would have left it at 0 and put every distance off without a word
        folder = _calibration_changed(plane_sequence, lambda data: data.update({typo: data.pop(meant, 40.0)}))
        with pytest.raises(SequenceError, match=re.escape(f"calib.yaml: unknown key {typo!r}, did you mean {meant!r}?")):
            read_calibration(folder)

    def test_notes_beside_the_calibration_are_left_alone(self, plane_sequence):
        info = plane_sequence([0.0])
        path = info["folder"] / "calib.yaml"
        path.write_text(path.read_text() + "serial: 12345\nfocal_mm: 2.1\nrecorded_by: line 3\n")
        assert read_calibration(info["folder"])["focal_px"] == pytest.approx(350.06)

    def test_an_alias_that_holds_itself_is_named_not_followed(self, plane_sequence):
        info = plane_sequence([0.0])
        path = info["folder"] / "calib.yaml"
        path.write_text(path.read_text() + "extra: &e [*e]\n")
        with pytest.raises(SequenceError, match=r"calib.yaml: not valid YAML \(an alias \(\*name\) refers to a node"):
            read_calibration(info["folder"])

    def test_a_camera_s_values_pass(self, plane_sequence):
        info = plane_sequence([0.0])
        path = info["folder"] / "calib.yaml"
        path.write_text(path.read_text().replace("width: 320", "width: 320.0"))  # a whole number, written as a float
        calib = read_calibration(info["folder"])
        assert calib["focal_px"] == pytest.approx(350.06) and calib["width"] == 320

    def test_an_exponent_without_a_decimal_point_is_a_number(self, plane_sequence):
        # YAML 1.1 reads 3e2 as a string; calibration tools write such values
        info = plane_sequence([0.0])
        path = info["folder"] / "calib.yaml"
        text = path.read_text()
        path.write_text(text.replace("width: 320", "width: 32e1").replace("doffs: 0.0", "doffs: 1e1"))
        calib = read_calibration(info["folder"])
        assert calib["width"] == 320 and isinstance(calib["width"], int) and calib["doffs"] == 10.0

    def test_a_number_yaml_reads_as_octal_is_named(self, plane_sequence):
        # YAML 1.1 reads 0320 as 208: a width with a leading zero was another camera's
        info = plane_sequence([0.0])
        path = info["folder"] / "calib.yaml"
        path.write_text(path.read_text().replace("width: 320", "width: 0320"))
        line = next(n for n, text in enumerate(path.read_text().splitlines(), 1) if text.startswith("width:"))
        with pytest.raises(SequenceError, match=re.escape(f"calib.yaml:{line}: width: 0320: YAML reads a leading zero "
                                                          f"as octal, 208; write 320 without the zero")):
            read_calibration(info["folder"])


    def test_a_byte_order_mark_is_read_past_and_a_byte_not_utf8_is_named(self, plane_sequence):
        # a calib.yaml with a Latin-1 comment ended in UnicodeDecodeError's traceback
        info = plane_sequence([0.0])
        path = info["folder"] / "calib.yaml"
        text = path.read_text()
        path.write_bytes(b"\xef\xbb\xbf" + text.encode())
        assert read_calibration(info["folder"])["width"] == 320
        path.write_bytes(text.encode() + b"# cam\xe9ra 2\n")
        line = text.count("\n") + 1
        with pytest.raises(SequenceError, match=re.escape(f"calib.yaml:{line}: calibration is not UTF-8 text (byte "
                                                          f"0xe9): save it as UTF-8")):
            read_calibration(info["folder"])

    def test_a_middlebury_calibration_with_a_byte_order_mark_is_read(self, tmp_path):
        # "\ufeffcam0" was no key: "not a Middlebury calibration ('cam0')"
        (tmp_path / "im0.png").write_bytes(b"")
        (tmp_path / "calib.txt").write_bytes(
            b"\xef\xbb\xbfcam0=[1000 0 300; 0 1000 200; 0 0 1]\r\ncam1=[1000 0 300; 0 1000 200; 0 0 1]\r\n"
            b"doffs=0\r\nbaseline=100\r\nwidth=640\r\nheight=400\r\nndisp=64\r\n")
        assert read_calibration(tmp_path)["focal_px"] == 1000.0

    def test_a_middlebury_key_given_twice_is_named(self, tmp_path):
        (tmp_path / "im0.png").write_bytes(b"")
        (tmp_path / "calib.txt").write_text("cam0=[1000 0 300; 0 1000 200; 0 0 1]\ndoffs=0\nbaseline=100\n"
                                            "width=640\nheight=400\nndisp=64\nbaseline=193\n")
        with pytest.raises(SequenceError, match=re.escape(
                "calib.txt:7: baseline: given twice (first at line 3); one of them would be ignored")):
            read_calibration(tmp_path)


class TestReadLabels:
    """``sequence_folder.read_labels``: the truth an evaluation compares with is checked, each problem one
    line naming the file and the entry."""

    def _write(self, tmp_path, labels) -> Path:
        path = tmp_path / "000001.json"
        path.write_text(labels if isinstance(labels, str) else json.dumps(labels))
        return path

    def test_a_byte_order_mark_is_read_past(self, tmp_path):
        # json refused it: "Unexpected UTF-8 BOM"
        path = tmp_path / "000001.json"
        path.write_bytes(b"\xef\xbb\xbf" + json.dumps({"defects": [{"class": "pit", "box": [1, 2, 3, 4]}]}).encode())
        assert read_labels(path)["defects"][0]["class"] == "pit"

    def test_a_good_label_reads_with_float_boxes(self, tmp_path):
        path = self._write(tmp_path, {"frame_id": "000001", "defects": [
            {"class": "crazing", "box": [1, 2, 30, 40], "distance_mm": 400, "deviation_mm": None}]})
        assert read_labels(path)["defects"][0]["box"] == [1.0, 2.0, 30.0, 40.0]

    @pytest.mark.parametrize("labels, message", [
        ("{not json", "000001.json: labels are not JSON"),
        # json keeps the last without a word: the truth a result is scored against must be the one written
        ('{"defects": [{"class": "pit", "box": [1, 2, 3, 4], "deviation_mm": 1, "deviation_mm": 2}]}',
         "000001.json: 'deviation_mm' given twice in one object; one of them would be ignored"),
        ('{"defects": ' + "[" * 100_000 + "]" * 100_000 + "}", "000001.json: labels nest deeper than JSON can be read"),
        ([1, 2], "000001.json: expected a mapping with a list of defects"),
        ({"defects": [{"box": [1, 2, 3, 4]}]}, "defects[0]: expected a mapping with a class name"),
        ({"defects": [{"class": "pit", "box": [1, 2, 3]}]}, "defects[0].box: expected [x0, y0, x1, y1]"),
        ({"defects": [{"class": "pit", "box": [5, 2, 3, 4]}]}, "defects[0].box: expected [x0, y0, x1, y1] with x0 < x1"),
        ({"defects": [{"class": "pit", "box": [1, 2, "a", 4]}]}, "defects[0].box"),
        ({"defects": [{"class": "pit", "box": [1, 2, 3, 4], "deviation_mm": "deep"}]},
         "defects[0].deviation_mm: expected a number or null, got 'deep'"),
        # a true distance of 0 divided the evaluation's floor by zero; a negative one was scored as a surface
        ({"defects": [{"class": "pit", "box": [1, 2, 3, 4], "distance_mm": 0}]},
         "defects[0].distance_mm: expected a number > 0 or null, got 0"),
        ({"defects": [{"class": "pit", "box": [1, 2, 3, 4], "distance_mm": -5}]},
         "defects[0].distance_mm: expected a number > 0 or null, got -5"),
        ({"defects": [], "sensor": "x"}, "000001.json: sensor: expected a mapping, got 'x'"),
        ({"defects": [], "sensor": {"noise_sigma": "a"}}, "sensor.noise_sigma: expected a number >= 0 or null"),
        ({"defects": [], "sensor": {"noise_sigma": -1}}, "sensor.noise_sigma: expected a number >= 0 or null"),
        ({"defects": [{"class": "pit", "box": [700, 2, 710, 4]}]},
         "defects[0].box: [700.0, 2.0, 710.0, 4.0] lies outside the 672x376 image"),
        ({"defects": [{"class": "pit", "box": [-9, 2, 0, 4]}]}, "defects[0].box: [-9.0, 2.0, 0.0, 4.0] lies outside"),
    ])
    def test_a_bad_label_is_one_line_naming_the_file_and_entry(self, tmp_path, labels, message):
        with pytest.raises(SequenceError) as info:
            read_labels(self._write(tmp_path, labels), (376, 672))
        assert message in str(info.value) and "\n" not in str(info.value)

    def test_a_box_partly_in_the_image_or_any_box_without_a_shape_reads(self, tmp_path):
        path = self._write(tmp_path, {"defects": [{"class": "pit", "box": [-5, -5, 10, 10]},
                                                  {"class": "pit", "box": [700, 2, 710, 4]}], "sensor": None})
        with pytest.raises(SequenceError):
            read_labels(path, (376, 672))
        assert len(read_labels(path)["defects"]) == 2
        path.write_text(json.dumps({"defects": [{"class": "pit", "box": [-5, -5, 10, 10]}]}))
        assert read_labels(path, (376, 672))["defects"][0]["box"] == [-5.0, -5.0, 10.0, 10.0]


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full on this system to answer writes with a full disk")
def test_a_frame_the_disk_refuses_is_an_error_naming_it_not_a_missing_frame(tmp_path):
    # cv2.imwrite's False went unchecked (and it is True for a small PNG that a full disk refuses at close):
    # `inspect camera record` and `inspect sim generate` reported pairs written that the sequence lacked
    import numpy as np

    from drivers.sequence_folder import write_frame

    (tmp_path / "left").mkdir()
    (tmp_path / "left" / "000001.png").symlink_to("/dev/full")
    image = np.zeros((8, 8, 3), np.uint8)
    write_frame(tmp_path, "000000", image, image)
    refused = f"{tmp_path / 'left' / '000001.png'}: could not be written (No space left on device)"
    with pytest.raises(OSError, match=re.escape(refused)):
        write_frame(tmp_path, "000001", image, image)
    assert not (tmp_path / "left" / "000001.png").exists() and not (tmp_path / "right" / "000001.png").exists()
