"""`inspect train average`: the mean of several checkpoints, loadable by the detector plugin."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch
from click.testing import CliRunner
from conftest import cli_here

from core.cli import _build
from plugins.yolov8.averaging import AveragingError, average_checkpoints, average_state_dicts
from untrained_yolo import NEU_NAMES as NAMES
from untrained_yolo import untrained_checkpoint


def _checkpoint(path, seed: int, nc: int = len(NAMES)):
    return untrained_checkpoint(path, nc=nc, seed=seed, vary_statistics=True)


def _float_params(path) -> dict[str, torch.Tensor]:
    checkpoint = torch.load(str(path), map_location="cpu", weights_only=False)
    module = checkpoint["ema"] if checkpoint.get("ema") is not None else checkpoint["model"]
    return {k: v for k, v in module.float().state_dict().items() if v.is_floating_point()}


@pytest.fixture(scope="module")
def two_checkpoints(tmp_path_factory):
    folder = tmp_path_factory.mktemp("ckpt")
    return _checkpoint(folder / "a.pt", 0), _checkpoint(folder / "b.pt", 1)


def test_state_dict_mean_is_weighted_and_keeps_integer_entries():
    a = {"w": torch.tensor([0.0, 2.0]), "n": torch.tensor(3)}
    b = {"w": torch.tensor([4.0, 6.0]), "n": torch.tensor(7)}
    assert torch.equal(average_state_dicts([a, b])["w"], torch.tensor([2.0, 4.0]))
    assert torch.equal(average_state_dicts([a, b], [0.25, 0.75])["w"], torch.tensor([3.0, 5.0]))
    assert average_state_dicts([a, b])["n"].item() == 3
    with pytest.raises(AveragingError, match="sum to 1"):
        average_state_dicts([a, b], [0.5, 0.6])


def test_averaged_checkpoint_holds_the_mean_and_detects(two_checkpoints, tmp_path):
    out = average_checkpoints(list(two_checkpoints), tmp_path / "mean.pt")
    a, b, mean = (_float_params(p) for p in (*two_checkpoints, out))
    assert mean.keys() == a.keys()
    differing = [k for k in a if not torch.equal(a[k], b[k])]
    assert len(differing) > len(a) // 2
    for key in differing:
        # saved in half precision, as ultralytics saves its own weights
        torch.testing.assert_close(mean[key], ((a[key] + b[key]) / 2).half().float(), atol=2e-3, rtol=2e-3)

    from core.contracts import PluginContext
    from core.registry import default_registry

    spec = default_registry().get("detector", "yolov8").spec
    detector = spec.factory({"weights": str(out), "imgsz": 128, "confidence": 0.0001}, PluginContext(device="cpu"))
    assert detector.class_names == NAMES
    assert detector.detect(torch.randint(0, 255, (128, 128, 3), dtype=torch.uint8).numpy())


def test_epoch_checkpoints_with_only_ema_weights_are_averaged(two_checkpoints, tmp_path):
    # what `--save-period` writes: the EMA weights, and model = None
    ema_only = torch.load(str(two_checkpoints[1]), map_location="cpu", weights_only=False)
    ema_only["ema"], ema_only["model"] = ema_only["model"], None
    torch.save(ema_only, str(tmp_path / "epoch3.pt"))
    out = average_checkpoints([two_checkpoints[0], tmp_path / "epoch3.pt"], tmp_path / "mean.pt")
    a, b, mean = (_float_params(p) for p in (*two_checkpoints, out))
    key = next(k for k in a if not torch.equal(a[k], b[k]))
    torch.testing.assert_close(mean[key], ((a[key] + b[key]) / 2).half().float(), atol=2e-3, rtol=2e-3)


def test_other_architecture_is_refused(two_checkpoints, tmp_path):
    other = _checkpoint(tmp_path / "three_classes.pt", 2, nc=3)
    with pytest.raises(AveragingError, match="checkpoint 2 has another architecture"):
        average_checkpoints([two_checkpoints[0], other], tmp_path / "mean.pt")
    assert not (tmp_path / "mean.pt").exists()


def test_checkpoints_of_another_class_list_are_refused(two_checkpoints, tmp_path):
    """The same shapes, the classes in another order: each output channel means another class in each."""
    from ultralytics import YOLO

    swapped = YOLO(str(two_checkpoints[1]))
    swapped.model.names = dict(enumerate([NAMES[1], NAMES[0], *NAMES[2:]]))
    swapped.save(str(tmp_path / "swapped.pt"))
    with pytest.raises(AveragingError, match=r"checkpoint 2 \(.*swapped.pt\) has classes \['inclusion', 'crazing',"):
        average_checkpoints([two_checkpoints[0], tmp_path / "swapped.pt"], tmp_path / "mean.pt")
    assert not (tmp_path / "mean.pt").exists()


def test_cli_averages_and_names_a_bad_file(two_checkpoints, tmp_path):
    runner = CliRunner()
    result = runner.invoke(_build(), ["train", "average", *map(str, two_checkpoints), "--out", str(tmp_path / "m.pt")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "m.pt").is_file()

    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint")
    result = runner.invoke(_build(), ["train", "average", str(two_checkpoints[0]), str(broken), "--out", str(tmp_path / "n.pt")])
    assert result.exit_code == 2
    assert "broken.pt: not a YOLO checkpoint" in result.output
    assert not (tmp_path / "n.pt").exists()

    result = runner.invoke(_build(), ["train", "average", str(two_checkpoints[0]), "--out", str(tmp_path / "n.pt")])
    assert result.exit_code == 2 and "at least two" in result.output


def test_a_checkpoint_given_twice_or_as_the_output_is_refused(two_checkpoints, tmp_path):
    # the mean weighed a repeated one twice, and --out overwrote an input with the mean
    first, second = map(str, two_checkpoints)
    before = Path(first).read_bytes()
    twice = cli_here("train", "average", first, second, first, "--out", str(tmp_path / "m.pt"))
    assert twice.returncode == 2 and twice.stderr == f"error: {first}: given twice\n", twice.stderr
    over = cli_here("train", "average", first, second, "--out", first)
    assert over.returncode == 2 and over.stderr == (f"error: --out {first}: the command reads that file: writing it "
                                                    f"would destroy it\n"), over.stderr
    assert Path(first).read_bytes() == before and not (tmp_path / "m.pt").exists()


@pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full (a device that is always full) here")
def test_a_checkpoint_the_disk_cannot_hold_is_named(two_checkpoints):
    # torch's own writer said "enforce fail at inline_container.cc" in a traceback
    with pytest.raises(AveragingError, match=r"^/dev/full: could not be written \(No space left on device\)$"):
        average_checkpoints(list(two_checkpoints), Path("/dev/full"))


def test_a_checkpoint_that_would_run_code_is_refused_and_never_run(two_checkpoints, tmp_path):
    # it was read with the whole pickle: averaging a file from elsewhere ran what it called
    from test_fail_safe import _booby_trapped_weights

    marker = tmp_path / "pwned"
    evil = _booby_trapped_weights(tmp_path / "evil.pt", marker)
    result = CliRunner().invoke(_build(), ["train", "average", str(two_checkpoints[0]), str(evil),
                                           "--out", str(tmp_path / "m.pt")])
    assert result.exit_code == 2 and "evil.pt: refused: reading it would call posix.system" in result.output
    assert "trust_pickle" not in result.output  # the detector's setting, which this command does not read
    assert not marker.exists(), "the checkpoint's pickle ran"
    assert not (tmp_path / "m.pt").exists()
