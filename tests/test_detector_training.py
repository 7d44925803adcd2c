"""`inspect train detector` on five NEU-DET fixture images: the schedule options reach ultralytics,
a run starts from earlier weights, and every epoch's weights are kept when asked."""
from __future__ import annotations

import yaml
from click.testing import CliRunner
from conftest import neu_fixture_dataset

from core.cli import _build
from untrained_yolo import untrained_checkpoint


def test_fine_tune_schedule_reaches_ultralytics_and_keeps_every_epoch(tmp_path):
    data = neu_fixture_dataset(tmp_path)
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
    # what a run writes passes the reading that refuses code: resuming, averaging epochs, --init from it
    from plugins.yolov8.detector import read_checkpoint

    for kept in ("epoch1.pt", "last.pt"):
        assert read_checkpoint(run / "weights" / kept, hint=None)


def test_weights_that_would_run_code_are_refused_before_training(tmp_path):
    # ultralytics' own loader reads the whole pickle: --init from a file from elsewhere ran what it called,
    # and so did a planted last.pt when the run resumed
    from test_fail_safe import _booby_trapped_weights

    data = neu_fixture_dataset(tmp_path)
    marker = tmp_path / "pwned"
    evil = _booby_trapped_weights(tmp_path / "evil.pt", marker)
    base = ["train", "detector", "--data", str(data), "--epochs", "1", "--device", "cpu", "--workers", "0",
            "--out", str(tmp_path / "runs"), "--name", "ft"]
    result = CliRunner().invoke(_build(), [*base, "--init", str(evil)])
    assert result.exit_code == 2 and f"--init {evil}: refused: reading it would call posix.system" in result.output
    last = tmp_path / "runs" / "ft" / "weights" / "last.pt"
    last.parent.mkdir(parents=True)
    _booby_trapped_weights(last, marker)
    result = CliRunner().invoke(_build(), base)
    assert result.exit_code == 2 and f"resuming from {last}: refused" in result.output, result.output
    assert not marker.exists(), "the checkpoint's pickle ran"


def test_a_label_line_ultralytics_would_drop_is_refused_before_training(tmp_path):
    # ultralytics drops such an image from training and says so only in its scan log
    data = neu_fixture_dataset(tmp_path)
    label = sorted((data / "labels" / "train").glob("*.txt"))[0]
    label.write_text(label.read_text() + "0 0.5 0.5 0.2\n")
    result = CliRunner().invoke(_build(), ["train", "detector", "--data", str(data), "--epochs", "1", "--device", "cpu",
                                           "--workers", "0", "--out", str(tmp_path / "runs")])
    assert result.exit_code == 2, result.output
    lines = len(label.read_text().splitlines())
    assert f"{label}: line {lines}: 4 numbers, expected 'class x y w h'" in result.output
    assert not (tmp_path / "runs").exists()
