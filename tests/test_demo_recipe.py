"""`inspect run recipes/steel_plate.yaml` as `make demo` runs it: the committed NEU-DET weights on
the committed synthetic sequence, the PLC simulator started in-process, the reject coil pulsed.

Every defect the detector reports is measured again, with the same box, on the generator's exact
disparity: the difference is the stereo + depth error alone, held to the opencv_sgbm tolerances of
test_sim_fixture_depth.py (1 % and 1.2 mm). At least three detections must be real defects
(IoU >= 0.3 with a labelled one).
"""
from __future__ import annotations

import json
import re
import socket
import sqlite3

import numpy as np
import pytest
from conftest import ROOT, cli

from core.depth import DepthRule, measure_defect
from core.types import Detection
from drivers.sequence_folder import read_calibration, read_disparity_png
from plugins.replay_camera import calibration_from_dict
from core.boxes import box_iou

FIXTURE = ROOT / "sim_fixtures" / "steel_plate"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    results = tmp_path_factory.mktemp("demo") / "results"
    port = _free_port()
    out = cli("run", str(ROOT / "recipes" / "steel_plate.yaml"), "--plc-sim",
              "--set", f"outputs.0.settings.port={port}", "--set", f"results.path={results}",
              # A slower belt (6 s to the actuator) so that a busy test machine is not late for it.
              "--set", "outputs.0.settings.conveyor_speed_mm_s=100",
              "--set", f"outputs.1.settings.file={results / 'rejects.log'}")
    return out, results, port


def test_demo_runs_and_summarises(demo):
    out, _, port = demo
    assert f"nothing listens on 127.0.0.1:{port}: starting the PLC simulator in-process" in out.stdout
    # the master parts, before the first plate: every defective one rejected
    assert re.search(r"master parts \S+steel_plate_masters: 4 inspected, (\d) of \1 defective ones rejected",
                     out.stdout), \
        out.stdout
    summary = re.search(r"parts 10  passed (\d+)  rejected (\d+)  errors (\d+)  alarms 0  [\d.]+ frames/s", out.stdout)
    assert summary, out.stdout + out.stderr
    # Exit 3 says some parts could not be inspected (and were rejected); otherwise 0.
    assert out.returncode == (3 if int(summary.group(3)) else 0), out.stdout + out.stderr
    lines = [l for l in out.stdout.splitlines() if re.match(r"R\d+-\d{6} frame", l)]
    assert len(lines) == 10
    for line in lines:
        if "no defect" not in line:
            # each defect's distance and deviation with its standard uncertainty
            assert re.search(r"Z=\d+\.\d±\d+\.\dmm dev=[+-]\d+\.\d\d±\d+\.\d\dmm", line), line


def test_every_reject_pulses_the_plc_coil(demo):
    out, results, _ = demo
    # ERROR parts could not be inspected: they are rejected like REJECT parts.
    rejects = len(re.findall(r"^R\d+-\d{6} frame \d+ (REJECT|ERROR)", out.stdout, re.M))
    assert out.stdout.count("coil 0 -> 1") == rejects
    db = sqlite3.connect(results / "results.db")
    sent = db.execute("SELECT COUNT(*) FROM output_events WHERE output='modbus' AND command LIKE 'write_coil 0 = 1%' AND outcome='delivered'").fetchone()[0]
    assert sent == rejects


def test_measurements_match_ground_truth(demo):
    _, results, _ = demo
    calib = calibration_from_dict(read_calibration(FIXTURE))
    db = sqlite3.connect(results / "results.db")
    measured = real = 0
    for frame_id, verdict, cls, x0, y0, x1, y1, distance, deviation, sigma in db.execute(
        "SELECT p.frame_id, p.verdict, d.class, d.x0, d.y0, d.x1, d.y1, d.distance_mm, d.deviation_mm,"
        " d.deviation_sigma_mm FROM defects d JOIN parts p ON p.id = d.part_row"
    ):
        truth = measure_defect(read_disparity_png(FIXTURE / "gt" / f"{frame_id}.png"), Detection(cls, 1.0, (x0, y0, x1, y1)), calib, DepthRule())
        if distance is None:
            # too few matched pixels in the box: no number, and a part that cannot be measured never passes
            assert verdict == "ERROR", (frame_id, cls)
            continue
        assert distance == pytest.approx(truth.distance_mm, rel=0.01), (frame_id, cls)
        if deviation is not None and truth.deviation_mm is not None:
            measured += 1
            # within 1.2 mm, or within twice the uncertainty the measurement states (a box over a
            # defect's wall says ± several mm, and its part is then undecided, so rejected)
            assert abs(deviation - truth.deviation_mm) <= max(1.2, 2 * sigma), (frame_id, cls, deviation, sigma,
                                                                               truth.deviation_mm)
        labels = json.loads((FIXTURE / "labels" / f"{frame_id}.json").read_text())["defects"]
        if labels and box_iou(np.array([[x0, y0, x1, y1]]), np.array([t["box"] for t in labels]))[0].max() >= 0.3:
            real += 1
    assert measured >= 5 and real >= 3
