"""plugins/yolov8/dataset_check.py: what ultralytics would drop from a dataset, judged as ultralytics' own
``verify_image_label`` judges it (which is called here, on copies, as the reference)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import neu_fixture_dataset
from PIL import Image

from plugins.yolov8.dataset_check import (dataset_problem, image_problem, label_file_problem, label_problem,
                                          resolved, shared_with_train)

CLASSES = 6

LABELS = {
    "a box": "0 0.5 0.5 0.2 0.2",
    "the last class": "5 0.5 0.5 0.2 0.2",
    "a class as a float": "2.0 0.5 0.5 0.2 0.2",
    "a class past the list": "6 0.5 0.5 0.2 0.2",
    "a negative class": "-1 0.5 0.5 0.2 0.2",
    "a fractional class": "1.5 0.5 0.5 0.2 0.2",
    "within ultralytics' 1 % beyond the edge": "0 1.005 0.5 0.2 0.2",
    "beyond it": "0 1.02 0.5 0.2 0.2",
    "slightly negative, sizes positive": "0 -0.005 0.5 0.2 0.2",
    "more negative": "0 -0.02 0.5 0.2 0.2",
    "a slightly negative size": "0 0.5 0.5 -0.005 0.2",
    "not a number": "0 0.5 zero 0.2 0.2",
    "nan": "0 nan 0.5 0.2 0.2",
    "infinite": "0 0.5 inf 0.2 0.2",
    "four numbers": "0 0.5 0.5 0.2",
    "six numbers": "0 0.5 0.5 0.2 0.2 0.1",
    "two rows": "0 0.5 0.5 0.2 0.2\n3 0.2 0.2 0.1 0.1",
    "a blank line between rows": "0 0.5 0.5 0.2 0.2\n\n3 0.2 0.2 0.1 0.1",
    "the same row twice": "0 0.5 0.5 0.2 0.2\n0 0.5 0.5 0.2 0.2",
    "a polygon": "1 0.1 0.1 0.4 0.1 0.4 0.3",
    "a polygon with an odd coordinate": "1 0.1 0.1 0.4 0.1 0.4 0.3 0.2",
    "a polygon and a box": "1 0.1 0.1 0.4 0.1 0.4 0.3\n0 0.5 0.5 0.2 0.2",
    "a polygon beyond the edge": "1 0.1 0.1 1.4 0.1 1.4 0.3",
    "a polygon slightly negative": "1 -0.005 0.1 0.4 0.1 0.4 0.3",
    "a byte-order mark": "\ufeff0 0.5 0.5 0.2 0.2",
    "empty": "",
}


def _ultralytics_drops(image: Path, label: Path) -> bool:
    from ultralytics.data.utils import verify_image_label

    result = verify_image_label((str(image), str(label), "", False, CLASSES, 0, 0, False))
    return result[8] == 1  # its count of corrupt samples


def _image(path: Path, size: int = 32) -> Path:
    Image.fromarray(np.full((size, size, 3), 128, np.uint8)).save(path)
    return path


class TestLabelFileProblem:
    @pytest.mark.parametrize("case", LABELS)
    def test_drops_exactly_what_ultralytics_drops(self, case, tmp_path):
        image = _image(tmp_path / "im.png")
        label = tmp_path / "im.txt"
        label.write_text(LABELS[case] + "\n", encoding="utf-8")
        why = label_file_problem(label, CLASSES)
        assert (why is not None) == _ultralytics_drops(image, label), why

    def test_names_the_line(self, tmp_path):
        label = tmp_path / "im.txt"
        label.write_text("0 0.5 0.5 0.2 0.2\n\n7 0.5 0.5 0.2 0.2\n")
        assert label_file_problem(label, CLASSES) == "line 3: class 7, but the dataset has classes 0-5"

    def test_a_file_that_is_not_text(self, tmp_path):
        label = tmp_path / "im.txt"
        label.write_bytes(b"\xff\xfe\x00\x81")
        assert "cannot be read as UTF-8 text" in label_file_problem(label, CLASSES)


class TestImageProblem:
    def test_a_good_image(self, tmp_path):
        assert image_problem(_image(tmp_path / "im.jpg")) is None

    @pytest.mark.parametrize("kind, expected", [("missing", "not found"), ("tiny", "under ultralytics' 10 px"),
                                                ("garbage", "not a readable image")])
    def test_drops_what_ultralytics_drops(self, kind, expected, tmp_path):
        image = tmp_path / "im.png"
        if kind == "tiny":
            _image(image, size=8)
        elif kind == "garbage":
            image.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
        label = tmp_path / "im.txt"
        label.write_text(LABELS["a box"])
        assert expected in image_problem(image)
        assert _ultralytics_drops(image, label)

    def test_reads_only(self, tmp_path):
        """ultralytics rewrites a JPEG without its end marker; the check leaves it as it is (and ultralytics keeps it)."""
        image = _image(tmp_path / "im.jpg")
        image.write_bytes(image.read_bytes()[:-2])
        before = image.read_bytes()
        assert image_problem(image) is None
        assert image.read_bytes() == before


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return neu_fixture_dataset(tmp_path_factory.mktemp("neu"))


class TestDatasetProblem:
    def _copy(self, dataset, tmp_path) -> Path:
        copy = tmp_path / "neu"
        shutil.copytree(dataset, copy)
        spec = (copy / "data.yaml").read_text().replace(f"path: {dataset}", f"path: {copy}")
        (copy / "data.yaml").write_text(spec)
        return copy

    def test_a_sound_dataset(self, dataset):
        assert dataset_problem(dataset / "data.yaml", ("train", "val")) is None

    def test_a_damaged_image_is_named_in_the_split_checked(self, dataset, tmp_path):
        copy = self._copy(dataset, tmp_path)
        image = sorted((copy / "images" / "val").iterdir())[0]
        image.write_bytes(b"not an image")
        assert dataset_problem(copy / "data.yaml", ("train",)) is None
        why = dataset_problem(copy / "data.yaml", ("val",))
        assert why.startswith(f"{image}: not a readable image") and why.endswith("ultralytics would leave such images out")

    def test_counts_the_other_images(self, dataset, tmp_path):
        copy = self._copy(dataset, tmp_path)
        labels = sorted((copy / "labels" / "val").glob("*.txt"))[:3]
        for label in labels:
            label.write_text("0 0.5 0.5 0.2\n")
        why = dataset_problem(copy / "data.yaml", ("val",))
        assert why.startswith(f"{labels[0]}: line 1: 4 numbers") and "(and 2 more images)" in why

    def test_the_model_classes(self, dataset):
        why = dataset_problem(dataset / "data.yaml", ("val",), ["a", "b"])
        assert why is not None and "are not the model's classes ['a', 'b']" in why


class TestLabelProblem:
    def test_an_image_listed_but_absent(self, tmp_path):
        images = tmp_path / "images"
        images.mkdir()
        _image(images / "a.png")
        (tmp_path / "labels").mkdir()
        (tmp_path / "labels" / "a.txt").write_text("0 0.5 0.5 0.2 0.2\n")
        listing = tmp_path / "val.txt"
        listing.write_text("images/a.png\nimages/gone.png\n")
        why = label_problem({"val": str(listing), "nc": CLASSES}, ("val",))
        assert why == f"{images / 'gone.png'}: not found; ultralytics would leave such images out"


    def test_a_split_without_images_is_named_with_the_dataset_file(self, tmp_path):
        # ultralytics said it in two lines and a link, after loading the model
        (tmp_path / "images").mkdir()
        why = label_problem({"val": str(tmp_path / "images"), "nc": CLASSES, "yaml_file": "data.yaml"}, ("val",))
        assert why == f"data.yaml: val: no image at {tmp_path / 'images'}: nothing to train or score on"


def test_ultralytics_neither_goes_online_nor_installs_packages_once_the_plugin_is_loaded():
    # an image Pillow could not identify made ultralytics pip-install pi-heif where the PC reached the internet
    code = ("import plugins.yolov8.dataset_check; from ultralytics.utils import AUTOINSTALL, ONLINE; "
            "print(AUTOINSTALL, ONLINE)")
    env = {k: v for k, v in os.environ.items() if not k.startswith("YOLO_")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120,
                         cwd=Path(__file__).resolve().parent.parent)
    assert out.stdout.split() == ["False", "False"], out.stdout + out.stderr


def test_an_image_pillow_cannot_identify_is_named(tmp_path):
    image = tmp_path / "im.webp"
    image.write_bytes(b"RIFF" + b"\x00" * 60)
    assert image_problem(image).startswith("not a readable image (")


class TestSharedWithTrain:
    def test_separate_splits(self, dataset):
        assert shared_with_train(resolved(dataset / "data.yaml"), "val") == 0

    def test_val_read_from_the_train_folder(self, dataset, tmp_path):
        spec = (dataset / "data.yaml").read_text().replace("val: images/val", "val: images/train")
        (tmp_path / "data.yaml").write_text(spec)
        assert "images/train" in spec and shared_with_train(resolved(tmp_path / "data.yaml"), "val") == len(
            list((dataset / "images" / "train").iterdir()))


class TestUnlabelledSplit:
    def test_a_split_without_any_label_file_is_refused(self, tmp_path):
        """Labels in a folder of another name than labels/: ultralytics finds none, and scores every box as a
        false positive on a defect-free image."""
        (tmp_path / "images").mkdir()
        (tmp_path / "annotations").mkdir()
        for name in ("a", "b"):
            _image(tmp_path / "images" / f"{name}.png")
            (tmp_path / "annotations" / f"{name}.txt").write_text("0 0.5 0.5 0.2 0.2\n")
        why = label_problem({"val": str(tmp_path / "images"), "nc": CLASSES}, ("val",))
        assert why is not None and why.startswith("val: none of its 2 images has a label file where ultralytics looks")
