"""`inspect train detector` on five NEU-DET fixture images: the schedule options reach ultralytics,
a run starts from earlier weights, and every epoch's weights are kept when asked."""
from __future__ import annotations

import shutil
from pathlib import Path

import yaml
from click.testing import CliRunner

from core.cli import _build
from plugins.yolov8.voc_to_yolo import convert_voc
from untrained_yolo import untrained_checkpoint

FIXTURES = Path(__file__).parent / "fixtures" / "neu_val"


def _dataset(tmp_path: Path) -> Path:
    src = tmp_path / "voc"
    (src / "images").mkdir(parents=True)
    (src / "annotations").mkdir()
    for image in FIXTURES.glob("*.jpg"):
        shutil.copy(image, src / "images")
        shutil.copy(image.with_suffix(".xml"), src / "annotations")
    stems = "\n".join(p.stem for p in FIXTURES.glob("*.jpg"))
    for split in ("train", "val"):
        (src / f"{split}.txt").write_text(stems)
    convert_voc(src, tmp_path / "yolo", {"train": src / "train.txt", "val": src / "val.txt"})
    return tmp_path / "yolo"


def test_fine_tune_schedule_reaches_ultralytics_and_keeps_every_epoch(tmp_path):
    data = _dataset(tmp_path)
    init = untrained_checkpoint(tmp_path / "init.pt")
    result = CliRunner().invoke(_build(), [
        "train", "detector", "--data", str(data), "--epochs", "2", "--imgsz", "64", "--batch", "4",
        "--device", "cpu", "--workers", "0", "--out", str(tmp_path / "runs"), "--name", "ft",
        "--init", str(init), "--optimizer", "AdamW", "--lr0", "0.0005", "--lrf", "1.0",
        "--warmup-epochs", "0", "--save-period", "1"])
    assert result.exit_code == 0, result.output
    run = tmp_path / "runs" / "ft"
    args = yaml.safe_load((run / "args.yaml").read_text())
    assert (args["optimizer"], args["lr0"], args["lrf"], args["warmup_epochs"]) == ("AdamW", 0.0005, 1.0, 0.0)
    assert args["model"] == str(init)
    weights = {p.name for p in (run / "weights").glob("*.pt")}
    assert {"epoch1.pt", "best.pt", "last.pt"} <= weights
