"""The fault-injection run in short form (``inspect sim faults``; the docs give the long one): damaged
frames, a PLC link cut at random through a TCP proxy, the process killed with SIGKILL and restarted, and
every part accounted for afterwards."""
from __future__ import annotations

import json
import random
import re

from conftest import cli, cli_here

from sim.faults import damaged_copy


def test_every_part_is_accounted_for_under_faults(tmp_path):
    out = tmp_path / "faults"
    result = cli("sim", "faults", str(out), "--parts", "40", "--kills", "1", "--damage", "0.2", "--seed", "3",
                 "--set", "stereo.backend=opencv_sgbm")
    assert result.returncode == 0, result.stdout + result.stderr
    report = json.loads((out / "faults.json").read_text())
    assert report["ok"] and report["parts"] >= 40 and report["runs"] == 2 and report["kills"] == 1
    assert report["damaged_frames"] and report["cuts"] >= 1
    assert report["delivered"] + report["alarmed"] >= report["rejected"] + report["errors"]
    assert report["crash_alarms"] >= 0 and report["integrity"] == "ok"
    assert "every part accounted for" in result.stdout


def test_the_damaged_copy_cuts_the_frames_it_names(tmp_path):
    damaged = damaged_copy(tmp_path / "seq", 2, 0.3, random.Random(1))
    assert damaged and len(list((tmp_path / "seq" / "left").iterdir())) == 20
    for frame_id in damaged:
        sizes = [(tmp_path / "seq" / eye / f"{frame_id}.jpg").read_bytes() for eye in ("left", "right")]
        assert any(not data.endswith(b"\xff\xd9") for data in sizes)


def test_a_line_that_cannot_run_is_one_line_naming_why(tmp_path):
    # a bad --set, and a run that ends by itself, ended in a RuntimeError's traceback
    result = cli_here("sim", "faults", str(tmp_path / "bad"), "--parts", "10", "--set", "nope=1")
    assert result.returncode == 2 and result.stderr.endswith("(--set nope): nope: unknown key\n"), result.stderr
    assert not (tmp_path / "bad").exists()  # said before anything was rendered or started
    result = cli("sim", "faults", str(tmp_path / "ends"), "--parts", "10", "--kills", "0", "--set",
                 "camera.settings.max_frames=1")
    # exit 0, or 4 where the harness's cut of the PLC link came before the one frame was done (a slow machine)
    assert result.returncode == 2 and re.fullmatch(r"error: inspect run ended by itself \(exit [04]\)\n",
                                                   result.stderr), result.stderr
    # 10^20 kills were drawn one by one before anything ran
    result = cli_here("sim", "faults", str(tmp_path / "kills"), "--parts", "10", "--kills", str(10**20))
    assert result.returncode == 2 and "--kills: at most one per part" in result.stderr, result.stderr
    assert not (tmp_path / "kills").exists()
