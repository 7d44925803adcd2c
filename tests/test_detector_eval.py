"""`inspect eval detector`: the committed weights scored on the committed NEU-DET val images, for real."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import ROOT, cli, cli_here, neu_fixture_dataset

WEIGHTS = ROOT / "models" / "yolov8n-neu-det.pt"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return neu_fixture_dataset(tmp_path_factory.mktemp("neu"))


def test_scores_the_committed_model_at_the_detectors_own_nms_iou(dataset, tmp_path):
    out = cli("eval", "detector", "--data", str(dataset), "--weights", str(WEIGHTS), "--out", str(tmp_path / "ev"))
    assert out.returncode == 0, out.stderr
    result = json.loads((tmp_path / "ev" / "detector_metrics.json").read_text())
    assert result["nms_iou"] == 0.5 and result["split"] == "val"  # 0.5 = YoloSettings.iou, what `inspect run` uses
    assert "also train images" not in out.stderr
    # The fixtures were chosen as images where the model finds the class: it must still do so.
    assert set(result["AP50"]) == {"inclusion", "patches", "pitted_surface", "rolled-in_scale", "scratches"}
    assert result["mAP50"] > 50.0
    assert 0.0 < result["mAP50-95"] < result["mAP50"]
    assert "NMS IoU 0.5" in out.stdout and "| mAP@0.50 |" in out.stdout and "| 70.0 |" in out.stdout
    assert (tmp_path / "ev" / "pr_curve.png").stat().st_size > 0
    md = (tmp_path / "ev" / "detector_metrics.md").read_text()
    assert f"| mAP@0.50 | {result['mAP50']:.1f} | 70.0 |" in md

    other = cli("eval", "detector", "--data", str(dataset), "--weights", str(WEIGHTS), "--iou", "0.7",
                "--out", str(tmp_path / "ev7"))
    assert other.returncode == 0, other.stderr
    assert json.loads((tmp_path / "ev7" / "detector_metrics.json").read_text())["nms_iou"] == 0.7


def test_scoring_on_training_images_is_said(dataset, tmp_path):
    spec = (dataset / "data.yaml").read_text().replace("val: images/val", "val: images/train")
    (tmp_path / "data.yaml").write_text(spec)
    out = cli("eval", "detector", "--data", str(tmp_path / "data.yaml"), "--weights", str(WEIGHTS),
              "--out", str(tmp_path / "ev"))
    assert out.returncode == 0, out.stderr
    trained = len(list((dataset / "images" / "train").iterdir()))
    assert f"{trained} of the val images are also train images: a score on them says how well the model" in out.stderr


def test_bad_input_is_one_line_naming_it(dataset, tmp_path):
    missing = cli_here("eval", "detector", "--data", str(dataset), "--weights", str(tmp_path / "none.pt"))
    assert missing.returncode == 2 and "none.pt: weights file not found" in missing.stderr
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint")
    bad = cli_here("eval", "detector", "--data", str(dataset), "--weights", str(broken), "--out", str(tmp_path / "ev"))
    assert bad.returncode == 2 and "broken.pt" in bad.stderr and "Traceback" not in bad.stderr
    nodata = cli_here("eval", "detector", "--data", str(tmp_path / "nodata"), "--weights", str(WEIGHTS))
    assert nodata.returncode == 2 and "nodata: dataset file not found" in nodata.stderr
    recipe = tmp_path / "recipe.yaml"  # a YAML file that is not a dataset: ultralytics raised with a traceback
    recipe.write_text("name: plate\ncamera: {plugin: replay}\n")
    wrong = cli_here("eval", "detector", "--data", str(recipe), "--weights", str(WEIGHTS))
    assert wrong.returncode == 2 and "Traceback" not in wrong.stderr
    assert f"{recipe}: not a YOLO dataset description: no val, names" in wrong.stderr
    twice = tmp_path / "twice.yaml"  # YAML keeps the second without a word: another split would be scored
    twice.write_text("val: images/val\nnames: [a]\nval: images/train\n")
    given = cli_here("eval", "detector", "--data", str(twice), "--weights", str(WEIGHTS))
    assert given.returncode == 2 and f"{twice}:3: val: given twice (first at line 1)" in given.stderr
    iou = cli_here("eval", "detector", "--data", str(dataset), "--weights", str(WEIGHTS), "--iou", "0")
    assert iou.returncode == 2 and "--iou" in iou.stderr


def test_a_dataset_the_scores_would_misread_is_refused(dataset, tmp_path):
    """Scored anyway, another class list gave each AP the model's name for another class, and a label line
    ultralytics drops took its image out of the scores, said only in ultralytics' own log."""
    import shutil

    copy = tmp_path / "neu"
    shutil.copytree(dataset, copy)
    spec = (copy / "data.yaml").read_text().replace(f"path: {dataset}", f"path: {copy}")
    (copy / "data.yaml").write_text(spec.replace("names:", "names: [a, b]\nold_names:", 1))
    other = cli_here("eval", "detector", "--data", str(copy), "--weights", str(WEIGHTS), "--out", str(tmp_path / "ev"))
    assert other.returncode == 2, other.stdout
    assert "data.yaml: names ['a', 'b'] are not the model's classes ['crazing', 'inclusion'," in other.stderr
    (copy / "data.yaml").write_text(spec)
    label = sorted((copy / "labels" / "val").glob("*.txt"))[0]
    label.write_text("7 0.5 0.5 0.2 0.2\n" + label.read_text())
    bad = cli_here("eval", "detector", "--data", str(copy), "--weights", str(WEIGHTS), "--out", str(tmp_path / "ev"))
    assert bad.returncode == 2, bad.stdout
    assert f"{label}: line 1: class 7, but the dataset has classes 0-5; ultralytics would leave such images out" in bad.stderr
    assert not (tmp_path / "ev" / "detector_metrics.json").exists()
