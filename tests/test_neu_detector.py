"""The committed NEU-DET weights, through the yolov8 plugin's defaults, on committed val images."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

from core.contracts import PluginContext
from core.registry import default_registry
from plugins.yolov8.detector import DEFAULT_WEIGHTS
from core.boxes import box_iou

FIXTURES = Path(__file__).resolve().parent / "fixtures" / "neu_val"
STEMS = sorted(p.stem for p in FIXTURES.glob("*.jpg"))


@pytest.fixture(scope="module")
def detector():
    # No weights in the settings: the plugin must load the committed model by default.
    return default_registry().get("detector", "yolov8").spec.factory({"tile_size": None}, PluginContext(device="cpu"))


def test_default_weights_are_the_committed_neu_model(detector):
    assert DEFAULT_WEIGHTS.name == "yolov8n-neu-det.pt" and DEFAULT_WEIGHTS.is_file()
    assert detector.class_names == ["crazing", "inclusion", "patches", "pitted_surface", "rolled-in_scale", "scratches"]


@pytest.mark.parametrize("stem", STEMS)
def test_finds_the_annotated_class(detector, stem):
    root = ET.parse(FIXTURES / f"{stem}.xml").getroot()
    truth = [(o.findtext("name"), [float(o.findtext(f"bndbox/{k}")) for k in ("xmin", "ymin", "xmax", "ymax")])
             for o in root.iter("object")]
    detections = detector.detect(cv2.imread(str(FIXTURES / f"{stem}.jpg")))
    expected = truth[0][0]
    hits = [d for d in detections if d.class_name == expected
            and box_iou(np.array([d.box]), np.array([b for c, b in truth if c == expected])).max() >= 0.5]
    assert hits, f"{stem}: no {expected} found; got {[(d.class_name, round(d.confidence, 2)) for d in detections]}"


def test_five_classes_covered():
    assert len(STEMS) == 5
