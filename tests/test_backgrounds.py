"""Background tiles for detector training: cut from a rendered sequence, clear of every defect."""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from core.cli import _build
from plugins.yolov8.backgrounds import clear_tiles
from plugins.yolov8.tiling import tile_origins
from sim.generate import generate_sequence


def test_clear_tiles_keep_away_from_boxes_by_the_margin():
    # 448x224 frame, 224 tiles, no overlap: two tiles, origins x = 0 and 224
    assert clear_tiles(224, 448, np.zeros((0, 4)), 224, 0.0, 0.0) == [(0, 0), (224, 0)]
    box = np.array([[10, 10, 50, 50]])
    assert clear_tiles(224, 448, box, 224, 0.0, 0.0) == [(224, 0)]
    near_border = np.array([[180, 10, 200, 50]])
    assert clear_tiles(224, 448, near_border, 224, 0.0, 10.0) == [(224, 0)]
    # grown by 30 px the box reaches x = 230, into the second tile too
    assert clear_tiles(224, 448, near_border, 224, 0.0, 30.0) == []


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    out = tmp_path_factory.mktemp("bg") / "plates"
    generate_sequence(out, frames=3, seed=5, width=448, height=300, neu_det=None)
    return out


def test_add_backgrounds_writes_clear_tiles_with_empty_labels(rendered, tmp_path):
    dataset = tmp_path / "data"
    (dataset / "images" / "train").mkdir(parents=True)
    (dataset / "labels").mkdir()
    (dataset / "labels" / "train.cache").write_text("stale")
    result = CliRunner().invoke(_build(), ["data", "add-backgrounds", str(rendered), str(dataset), "--margin", "16"])
    assert result.exit_code == 0, result.output
    images = sorted((dataset / "images" / "train").glob("bg_plates_*.jpg"))
    assert images and f"{len(images)} background tiles from 3 frames" in result.output
    assert not (dataset / "labels" / "train.cache").exists()
    expected = 0
    for label in (rendered / "labels").glob("*.json"):
        boxes = np.array([d["box"] for d in json.loads(label.read_text())["defects"]]).reshape(-1, 4)
        expected += len(clear_tiles(300, 448, boxes, 224, 0.25, 16.0))
    per_frame = len(tile_origins(300, 224, 0.25)) * len(tile_origins(448, 224, 0.25))
    assert len(images) == expected < 3 * per_frame  # the rendered defects keep some tiles out
    for image in images:
        _, frame_id, x0, y0 = image.stem.rsplit("_", 3)
        x0, y0 = int(x0), int(y0)
        assert (dataset / "labels" / "train" / f"{image.stem}.txt").read_text() == ""
        tile = cv2.imread(str(image))
        assert tile.shape[:2] == (224, 224)
        frame = cv2.imread(str(next((rendered / "left").glob(f"{frame_id}.*"))))
        assert np.abs(tile.astype(int) - frame[y0:y0 + 224, x0:x0 + 224].astype(int)).mean() < 3  # JPEG only
        for defect in json.loads((rendered / "labels" / f"{frame_id}.json").read_text())["defects"]:
            bx0, by0, bx1, by1 = defect["box"]
            assert bx1 + 16 <= x0 or bx0 - 16 >= x0 + 224 or by1 + 16 <= y0 or by0 - 16 >= y0 + 224


def test_add_backgrounds_errors_name_the_folder(rendered, tmp_path):
    result = CliRunner().invoke(_build(), ["data", "add-backgrounds", str(rendered), str(tmp_path / "nodata")])
    assert result.exit_code == 2 and "nodata/images/train" in result.output
    dataset = tmp_path / "data"
    (dataset / "images" / "train").mkdir(parents=True)
    result = CliRunner().invoke(_build(), ["data", "add-backgrounds", str(tmp_path), str(dataset)])
    assert result.exit_code == 2 and "labels: no frame labels" in result.output and "--all-clear" in result.output


def test_recorded_sound_parts_give_every_tile(rendered, tmp_path):
    recorded = tmp_path / "recorded"
    (recorded / "left").mkdir(parents=True)
    for image in (rendered / "left").glob("*"):
        (recorded / "left" / image.name).write_bytes(image.read_bytes())
    dataset = tmp_path / "data"
    (dataset / "images" / "train").mkdir(parents=True)
    result = CliRunner().invoke(_build(), ["data", "add-backgrounds", str(recorded), str(dataset), "--all-clear"])
    assert result.exit_code == 0, result.output
    per_frame = len(tile_origins(300, 224, 0.25)) * len(tile_origins(448, 224, 0.25))
    assert len(list((dataset / "images" / "train").glob("bg_recorded_*.jpg"))) == 3 * per_frame


def _recorded(rendered, folder):
    (folder / "left").mkdir(parents=True)
    for image in (rendered / "left").glob("*"):
        (folder / "left" / image.name).write_bytes(image.read_bytes())
    return folder


def _dataset(folder):
    (folder / "images" / "train").mkdir(parents=True)
    return folder


def test_a_frame_that_cannot_be_read_adds_nothing(rendered, tmp_path):
    # its tiles came after the frames before it had been added: half a sequence's backgrounds
    recorded = _recorded(rendered, tmp_path / "recorded")
    last = sorted((recorded / "left").glob("*"))[-1]
    last.write_bytes(last.read_bytes()[:3000])
    dataset = _dataset(tmp_path / "data")
    result = CliRunner().invoke(_build(), ["data", "add-backgrounds", str(recorded), str(dataset), "--all-clear"])
    assert result.exit_code == 2 and f"{last}: left image of frame {last.stem} is not whole" in result.output
    assert list((dataset / "images" / "train").iterdir()) == []


def test_a_labelled_box_off_its_image_adds_nothing(rendered, tmp_path):
    # the defect it stood for was left unmasked, and the tiles over it went in as plate without a defect
    sequence = tmp_path / "plates"
    shutil.copytree(rendered, sequence)
    label_path = sorted((sequence / "labels").glob("*.json"))[-1]
    label = json.loads(label_path.read_text())
    label["defects"][0]["box"] = [1000.0, 1000.0, 1200.0, 1100.0]
    label_path.write_text(json.dumps(label))
    dataset = _dataset(tmp_path / "data")
    result = CliRunner().invoke(_build(), ["data", "add-backgrounds", str(sequence), str(dataset)])
    assert result.exit_code == 2
    assert f"{label_path}: defects[0].box: [1000.0, 1000.0, 1200.0, 1100.0] lies outside the 448x300 image" in result.output
    assert list((dataset / "images" / "train").iterdir()) == []


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full (a device that is always full) here")
def test_a_tile_the_disk_refuses_removes_the_tiles_added_before_it(rendered, tmp_path):
    recorded = _recorded(rendered, tmp_path / "recorded")
    dataset = _dataset(tmp_path / "data")
    # the last tile of the last frame lands on a full disk
    x0, y0 = tile_origins(448, 224, 0.25)[-1], tile_origins(300, 224, 0.25)[-1]
    refused = dataset / "images" / "train" / f"bg_recorded_{sorted((recorded / 'left').glob('*'))[-1].stem}_{x0}_{y0}.jpg"
    refused.symlink_to("/dev/full")
    result = CliRunner().invoke(_build(), ["data", "add-backgrounds", str(recorded), str(dataset), "--all-clear"])
    per_frame = len(tile_origins(300, 224, 0.25)) * len(tile_origins(448, 224, 0.25))
    assert result.exit_code == 2 and result.output == (
        f"error: {refused}: could not be written (No space left on device); the {3 * per_frame - 1} tiles added "
        f"before it were removed again\n"), result.output
    assert list((dataset / "images" / "train").iterdir()) == [] and list((dataset / "labels" / "train").iterdir()) == []
    assert Path("/dev/full").exists()
