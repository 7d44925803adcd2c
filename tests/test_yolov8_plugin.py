"""The yolov8 detector plugin on an untrained YOLOv8n built from ultralytics' own architecture file
(no download): loading, whole-frame and tiled inference, boxes in frame coordinates."""
from __future__ import annotations

import os
import re

import numpy as np
import pytest

from core.contracts import PluginContext
from core.registry import default_registry
from core.types import Detection
from plugins.yolov8.detector import DetectionLimit
from untrained_yolo import NEU_NAMES as NAMES
from untrained_yolo import untrained_checkpoint


@pytest.fixture(scope="module")
def untrained_weights(tmp_path_factory):
    return untrained_checkpoint(tmp_path_factory.mktemp("w") / "untrained.pt")


def _detector(weights, **settings):
    spec = default_registry().get("detector", "yolov8").spec
    return spec.factory({"weights": str(weights), **settings}, PluginContext(device="cpu"))


def test_loads_weights_and_class_names(untrained_weights):
    assert _detector(untrained_weights).class_names == NAMES


@pytest.mark.parametrize("tile_size", [None, 128])
def test_boxes_are_in_frame_coordinates(untrained_weights, tile_size):
    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (200, 336, 3), dtype=np.uint8)
    # An untrained head scores everything low; a tiny threshold still makes it return boxes.
    detector = _detector(untrained_weights, tile_size=tile_size, imgsz=128, confidence=0.0001, max_det=300)
    detections = detector.detect(image)
    assert detections and all(isinstance(d, Detection) for d in detections)
    assert all(d.class_name in NAMES for d in detections)
    assert all(-1 <= d.box[0] < d.box[2] <= 337 and -1 <= d.box[1] < d.box[3] <= 201 for d in detections)
    assert [d.confidence for d in detections] == sorted((d.confidence for d in detections), reverse=True)
    if tile_size:
        assert max(d.box[2] for d in detections) > 128  # boxes from tiles beyond the first were shifted


@pytest.mark.parametrize("tile_size", [None, 128])
def test_an_image_with_as_many_boxes_as_max_det_is_an_error_not_a_cut_list(untrained_weights, tile_size):
    """The network stops at max_det boxes, the most confident first: a defect beyond them was never reported,
    and its part passed on the ones that were."""
    image = np.random.default_rng(0).integers(0, 255, (200, 336, 3), dtype=np.uint8)
    detector = _detector(untrained_weights, tile_size=tile_size, imgsz=128, confidence=0.0001, max_det=3)
    with pytest.raises(DetectionLimit, match=r"the detector reached its max_det of 3 boxes in one image: more may have "
                                           r"been left out \(raise detector.settings.max_det\)"):
        detector.detect(image)


def test_a_whole_frame_is_seen_at_its_long_side_up_to_960_px(untrained_weights, monkeypatch):
    """A 2K frame fed at its own 2208 px showed the committed model its defects at twice the scale it finds them at."""
    from plugins.yolov8.detector import YoloDetector

    sizes = []
    original = YoloDetector._predict

    def recording(self, images, imgsz):
        sizes.append((images[0].shape[1], imgsz))
        return original(self, images, imgsz)

    monkeypatch.setattr(YoloDetector, "_predict", recording)
    for width, height, imgsz in ((672, 376, None), (1280, 720, None), (2208, 1242, None), (2208, 1242, 1280)):
        _detector(untrained_weights, tile_size=None, imgsz=imgsz).detect(np.zeros((height, width, 3), np.uint8))
    assert sizes == [(672, 672), (1280, 960), (2208, 960), (2208, 1280)]


def test_missing_weights_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.pt: detector weights not found"):
        _detector(tmp_path / "nope.pt")


@pytest.mark.parametrize("architecture, says", [
    ("yolov8n-cls.yaml", "the checkpoint of a YOLO classify model, not a detector's: it gives one class per image"),
    ("yolov8n-obb.yaml", "the checkpoint of a YOLO obb model, not a detector's: it gives rotated boxes"),
])
def test_a_checkpoint_of_a_model_that_gives_no_boxes_is_refused_at_load(tmp_path, architecture, says):
    # validated as a detector's, it made every part an ERROR at its first detection
    os.environ.setdefault("YOLO_OFFLINE", "1")
    from ultralytics import YOLO

    from plugins.yolov8.detector import checkpoint_class_names

    weights = tmp_path / "other.pt"
    YOLO(architecture).save(str(weights))
    with pytest.raises(ValueError, match=re.escape(says)):
        _detector(weights)
    with pytest.raises(ValueError, match=re.escape(says)):  # what inspect validate asks
        checkpoint_class_names(weights)


def test_a_device_is_one_torch_knows_and_has(untrained_weights):
    # another name, or cuda on a machine without it, failed every part's detection, each an ERROR
    from pydantic import ValidationError

    from plugins.yolov8.detector import YoloSettings

    assert YoloSettings.model_validate({"device": 0}).device == "0"  # ultralytics' own form
    with pytest.raises(ValidationError, match="'banana': one of auto, cpu, cuda, cuda:N"):
        YoloSettings.model_validate({"device": "banana"})
    import torch

    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="device 'cuda:0': torch sees no CUDA device on this machine"):
            _detector(untrained_weights, device="cuda:0")


def test_the_warm_up_sets_the_predictor_up_before_the_first_part(untrained_weights):
    # the engine calls a detector's optional warm_up, never detect, before the parts (core/engine.py, Pipeline)
    detector = _detector(untrained_weights, tile_size=None, imgsz=64)
    assert detector.model.predictor is None
    detector.warm_up()
    assert detector.model.predictor is not None


def test_detection_leaves_torch_thread_count_alone(untrained_weights):
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        _detector(untrained_weights, tile_size=None, imgsz=64).detect(np.zeros((64, 64, 3), np.uint8))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_full_tile_boxes_are_dropped_when_tiling():
    from plugins.yolov8.detector import _without_full_tile

    boxes = np.array([[0, 0, 224, 224], [1, 2, 220, 223], [10, 10, 60, 224], [0, 0, 224, 100]], np.float32)
    kept, scores, classes = _without_full_tile((boxes, np.ones(4), np.zeros(4, int)), 224 * 0.95)
    assert kept.tolist() == [[10, 10, 60, 224], [0, 0, 224, 100]]


def test_importing_ultralytics_keeps_thread_settings():
    import subprocess
    import sys

    code = ("import torch, cv2; from plugins.yolov8.detector import import_yolo; n = cv2.getNumThreads(); "
            "import_yolo(); print(torch.get_num_threads(), cv2.getNumThreads() == n)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"})
    threads, cv_same = out.stdout.split()
    assert int(threads) == torch_default_threads() and cv_same == "True"


def torch_default_threads() -> int:
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", "import torch; print(torch.get_num_threads())"], capture_output=True,
                         text=True, check=True, env={k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"})
    return int(out.stdout)
