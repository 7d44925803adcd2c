"""VOC -> YOLO on hand-written annotations with each real-world fault."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import yaml
from conftest import cli, cli_here, png_declaring

from plugins.yolov8.voc_to_yolo import convert_voc

XML = """<annotation><filename>{stem}.jpg</filename><size><width>200</width><height>200</height><depth>1</depth></size>
{objects}</annotation>"""
OBJ = "<object><name>{name}</name><bndbox><xmin>{x0}</xmin><ymin>{y0}</ymin><xmax>{x1}</xmax><ymax>{y1}</ymax></bndbox></object>"


def _dataset(root: Path) -> Path:
    src = root / "voc"
    (src / "images").mkdir(parents=True)
    (src / "annotations").mkdir()
    img = np.full((200, 200, 3), 128, np.uint8)

    def add(stem, objects, image=True, xml=True):
        if image:
            cv2.imwrite(str(src / "images" / f"{stem}.jpg"), img)
        if xml:
            body = "".join(OBJ.format(name=n, x0=a, y0=b, x1=c, y1=d) for n, (a, b, c, d) in objects)
            (src / "annotations" / f"{stem}.xml").write_text(XML.format(stem=stem, objects=body))

    # File name says crazing, the box says patches: the label must come from the XML.
    add("crazing_1", [("patches", (10, 20, 110, 120))])
    add("good_2", [("scratches", (0, 0, 50, 200)), ("inclusion", (150, 150, 180, 190))])
    add("outside_3", [("scratches", (-10, 20, 250, 60))])
    add("empty_4", [("inclusion", (50, 50, 50, 80)), ("inclusion", (10, 10, 40, 40))])
    add("unknown_5", [("rust", (10, 10, 40, 40))])
    add("noxml_6", [], xml=False)
    add("noimage_7", [("patches", (1, 1, 9, 9))], image=False)
    (src / "images" / "malformed_8.jpg").write_bytes(cv2.imencode(".jpg", img)[1].tobytes())
    (src / "annotations" / "malformed_8.xml").write_text("<annotation><object><name>patches</name>")
    # 'nan' reads as a float: its label line was "2 nan 0.35 nan 0.5"
    add("nan_9", [("patches", ("nan", 20, 110, 120)), ("patches", (10, 20, 110, 120))])
    # cut short: it decoded as the picture padded with grey, and went into the training set
    add("truncated_10", [("patches", (10, 20, 110, 120))])
    cut = src / "images" / "truncated_10.jpg"
    cut.write_bytes(cut.read_bytes()[:300])
    return src


def _labels(dst: Path, stem: str) -> list[list[float]]:
    return [list(map(float, line.split())) for line in (dst / "labels" / "train" / f"{stem}.txt").read_text().splitlines()]


def test_faults_reported_none_fatal(tmp_path):
    src = _dataset(tmp_path)
    dst = tmp_path / "yolo"
    report = convert_voc(src, dst)
    assert report.faults == {
        "box_clamped": 1, "empty_box": 1, "unknown_class": 1, "image_without_xml": 1,
        "xml_without_image": 1, "malformed_xml": 2, "truncated_image": 1,
    }
    messages = "\n".join(report.messages)
    for name in ("outside_3.xml", "empty_4.xml", "unknown_5.xml", "noxml_6", "noimage_7.xml", "malformed_8.xml"):
        assert name in messages
    assert "nan_9.xml object 0: bndbox [nan, 20.0, 110.0, 120.0] is not finite" in messages
    assert "truncated_image: truncated_10.jpg: truncated JPEG (no end-of-image marker)" in messages
    assert not (dst / "images" / "train" / "truncated_10.jpg").exists()
    assert _labels(dst, "nan_9") == [[2, 0.3, 0.35, 0.5, 0.5]]
    assert _labels(dst, "crazing_1") == [[2, 0.3, 0.35, 0.5, 0.5]]
    assert _labels(dst, "outside_3") == [[5, 0.5, 0.2, 1.0, 0.2]]
    assert len(_labels(dst, "empty_4")) == 1 and _labels(dst, "unknown_5") == []
    data = yaml.safe_load((dst / "data.yaml").read_text())
    assert data["names"][2] == "patches" and data["train"] == "images/train"
    assert report.images == 6  # malformed and the two orphans are left out


def test_split_files_and_cli(tmp_path):
    src = _dataset(tmp_path)
    (src / "train.txt").write_text("crazing_1\ngood_2\n")
    (src / "val.txt").write_text("outside_3\n")
    out = cli("data", "convert-voc", str(src), str(tmp_path / "y"), "--split-files", "train.txt", "val.txt")
    assert out.returncode == 0, out.stderr
    assert "converted 3 images" in out.stdout and "box_clamped" in out.stdout
    assert "warning: box_clamped: outside_3.xml" in out.stderr
    assert sorted(p.name for p in (tmp_path / "y" / "labels" / "val").iterdir()) == ["outside_3.txt"]


def test_the_sources_own_split_files_are_used_and_their_absence_said(tmp_path):
    """NEU-DET ships train.txt and val.txt beside its folders: without them val was the training images,
    and a detector's score on it a score on what it had learnt."""
    src = _dataset(tmp_path)
    (src / "train.txt").write_text("crazing_1\ngood_2\n")
    (src / "val.txt").write_text("outside_3\n")
    out = cli("data", "convert-voc", str(src), str(tmp_path / "y"))
    assert out.returncode == 0, out.stderr
    assert f"splits: {src / 'train.txt'}, {src / 'val.txt'}" in out.stdout
    assert sorted(p.name for p in (tmp_path / "y" / "labels" / "val").iterdir()) == ["outside_3.txt"]
    (src / "val.txt").unlink()
    out = cli("data", "convert-voc", str(src), str(tmp_path / "z"))
    assert out.returncode == 0, out.stderr
    assert "no --split-files were given: every image is in train, and val is the same images" in out.stderr


def test_split_files_a_windows_editor_saved_are_read_and_others_refused(tmp_path):
    # the byte-order mark Notepad writes made the first stem "\ufeffcrazing_1", listed but not found, and
    # that image was in neither split; a file not in UTF-8 ended in a traceback
    src = _dataset(tmp_path)
    (src / "train.txt").write_bytes(b"\xef\xbb\xbfcrazing_1\r\ngood_2\r\n")
    (src / "val.txt").write_bytes(b"outside_3\n")
    out = cli("data", "convert-voc", str(src), str(tmp_path / "y"))
    assert out.returncode == 0, out.stderr
    assert sorted(p.name for p in (tmp_path / "y" / "labels" / "train").iterdir()) == ["crazing_1.txt", "good_2.txt"]
    (src / "val.txt").write_bytes(b"outside_3\nr\xe9ject\n")
    out = cli_here("data", "convert-voc", str(src), str(tmp_path / "z"))
    assert out.returncode == 2 and out.stderr == (f"error: {src / 'val.txt'}:2: split file is not UTF-8 text (byte 0xe9): "
                                                  f"save it as UTF-8\n"), out.stderr


def test_another_tools_xml_is_a_fault_not_an_image_without_defects(tmp_path):
    src = _dataset(tmp_path)
    (src / "annotations" / "crazing_1.xml").write_text("<labelme><shape>patches</shape></labelme>")
    report = convert_voc(src, tmp_path / "yolo")
    assert "malformed_xml: crazing_1.xml: root element <labelme>, not a VOC <annotation>" in report.messages
    assert not (tmp_path / "yolo" / "labels" / "train" / "crazing_1.txt").exists()  # was an empty label file


def test_split_files_that_repeat_share_or_empty_a_split_are_said(tmp_path):
    # a stem listed twice was converted twice and counted twice; one in both splits scored val on a training
    # image unsaid; a split without a usable image gave a dataset nothing could be trained or scored on
    src = _dataset(tmp_path)
    (src / "train.txt").write_text("crazing_1\ngood_2\ncrazing_1\n")
    (src / "val.txt").write_text("outside_3\ngood_2\n")
    report = convert_voc(src, tmp_path / "y", {"train": src / "train.txt", "val": src / "val.txt"})
    assert "listed_twice: crazing_1: listed twice in train (train.txt), converted once" in report.messages
    assert ("in_two_splits: good_2: listed in train and in val: a score on val then counts an image the model was "
            "trained on") in report.messages
    assert report.images == 4 and "empty_split" not in report.faults
    (src / "val.txt").write_text("truncated_10\n\n")
    report = convert_voc(src, tmp_path / "z", {"train": src / "train.txt", "val": src / "val.txt"})
    assert "empty_split: val: no image of the split could be converted" in report.messages
    assert report.faults["empty_split"] == 1  # train has its images


def test_an_image_declaring_more_pixels_than_any_camera_is_a_fault_not_decoded(tmp_path):
    src = _dataset(tmp_path)
    (src / "images" / "good_2.jpg").unlink()
    (src / "images" / "good_2.png").write_bytes(png_declaring(10_000, 7_000))  # 70 KB, 210 MB decoded
    report = convert_voc(src, tmp_path / "yolo")
    assert "unreadable_image: good_2.png: declares more than 64 MP" in report.messages
