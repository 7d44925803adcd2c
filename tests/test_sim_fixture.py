"""The committed demo sequence ``sim_fixtures/steel_plate`` and NEU-DET crops (skipped without NEU-DET)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from core.depth import DepthRule, measure_defect
from core.types import Calibration, Detection
from drivers.sequence_folder import list_frames, read_calibration, read_disparity_png, read_image
from sim.neu_crops import NEU_CLASSES, NeuCrops, parse_voc

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "sim_fixtures" / "steel_plate"
NEU_DET = ROOT.parent / "shared" / "data" / "neu-det"
needs_neu = pytest.mark.skipif(not (NEU_DET / "val.txt").exists(), reason="NEU-DET not available at ../shared")


def test_fixture_is_a_complete_labelled_sequence():
    size = sum(p.stat().st_size for p in FIXTURE.rglob("*") if p.is_file())
    assert size < 6_000_000
    c = read_calibration(FIXTURE)
    calib = Calibration(c["focal_px"], c["baseline_mm"], c["cx"], c["cy"], c["width"], c["height"], c["doffs"])
    assert (calib.width, calib.height, calib.focal_px, calib.baseline_mm) == (672, 376, 350.06, 120.0)
    frames = list_frames(FIXTURE)
    assert len(frames) == 10
    verdicts = []
    for f in frames:
        assert f.left and f.right and f.gt and f.labels
        assert read_image(f.left).shape == (376, 672, 3)
        gt = read_disparity_png(f.gt)
        labels = json.loads(f.labels.read_text())
        assert labels["frame_id"] == f.frame_id and 380 <= labels["distance_mm"] <= 450
        for d in labels["defects"]:
            assert d["class"] in NEU_CLASSES and d["source"] != "synthetic"
            m = measure_defect(gt, Detection(d["class"], 1.0, tuple(d["box"])), calib, DepthRule())
            assert m.deviation_mm == pytest.approx(d["deviation_mm"], abs=1e-3)
            assert m.distance_mm == pytest.approx(d["distance_mm"], abs=1e-3)
        verdicts.append(any(abs(d["deviation_mm"]) > 1.0 for d in labels["defects"]))
    assert 3 <= sum(verdicts) <= 7  # both verdicts at a 1 mm deviation limit


@needs_neu
def test_neu_classes_come_from_the_xml():
    crops = NeuCrops(NEU_DET)
    assert set(crops.by_class) == set(NEU_CLASSES)
    mismatched = 0
    for cls, boxes in crops.by_class.items():
        for b in boxes:
            assert b.stem in crops.stems
            names = [n for n, box in parse_voc(NEU_DET / "annotations" / f"{b.stem}.xml") if box == b.box]
            assert cls in names
            mismatched += not b.stem.startswith(cls)
    assert mismatched > 0  # NEU-DET has boxes whose class differs from their file name
    patch, (x0, y0, x1, y1) = crops.patch(crops.pick(np.random.default_rng(0), "scratches"))
    assert patch.dtype == np.float32 and 0 <= x0 < x1 <= patch.shape[1] and 0 <= y0 < y1 <= patch.shape[0]


@needs_neu
def test_generate_with_neu_crops(tmp_path):
    from sim.generate import generate_sequence

    labels = generate_sequence(tmp_path / "s", frames=4, seed=1, neu_det=NEU_DET, width=320, height=180)
    sources = [d["source"] for lab in labels for d in lab["defects"]]
    stems = set((NEU_DET / "val.txt").read_text().split())
    assert sources and all(s in stems for s in sources)


def test_a_neu_image_cut_short_is_named_not_rendered_half_grey(tmp_path):
    import cv2

    from sim.neu_crops import NeuDetError

    (tmp_path / "images").mkdir()
    (tmp_path / "annotations").mkdir()
    (tmp_path / "val.txt").write_text("crazing_1\n")
    (tmp_path / "annotations" / "crazing_1.xml").write_text(
        "<annotation><object><name>crazing</name><bndbox><xmin>10</xmin><ymin>10</ymin><xmax>90</xmax>"
        "<ymax>90</ymax></bndbox></object></annotation>")
    image = np.random.default_rng(0).integers(0, 255, (200, 200), np.uint8)
    data = cv2.imencode(".jpg", image)[1].tobytes()
    path = tmp_path / "images" / "crazing_1.jpg"
    path.write_bytes(data)
    assert NeuCrops(tmp_path).image("crazing_1").shape == (200, 200)
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(NeuDetError, match=r"crazing_1\.jpg: not whole: truncated JPEG"):
        NeuCrops(tmp_path).image("crazing_1")
