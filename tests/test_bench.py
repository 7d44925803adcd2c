from __future__ import annotations

import json

from conftest import ROOT, cli


def test_bench_times_every_stage_and_saves_tables(tmp_path):
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "opencv_sgbm",
              "--frames", "2", "--repeats", "2", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "bench-wvga-cpu.json").read_text())
    result = report["results"][0]
    assert result["backend"] == "opencv_sgbm" and result["frames"] == 2 and result["repeats"] == 2
    stages = result["stages_ms"]
    assert set(stages) == {"capture", "detection", "stereo", "depth", "decision", "outputs", "loop"}
    assert all(s["min"] <= s["median"] <= s["max"] for s in stages.values())
    parts = sum(stages[k]["median"] for k in stages if k != "loop")
    assert abs(parts - stages["loop"]["median"]) < 0.05 * stages["loop"]["median"] + 1.0
    assert stages["stereo"]["median"] > 0 and result["fps"] > 0 and result["peak_rss_mb"] > 0
    assert report["machine"]["cores"] >= 1 and report["resolution"] == "672x376"
    assert "| opencv_sgbm |" in (tmp_path / "bench-wvga-cpu.md").read_text()


def test_bench_hd720_and_unknown_backend(tmp_path):
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "nope", "--out", str(tmp_path))
    assert out.returncode == 2 and "unknown stereo backend nope" in out.stderr
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "opencv_sgbm",
              "--resolution", "hd720", "--frames", "1", "--repeats", "1", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "bench-hd720-cpu.json").read_text())["resolution"] == "1280x720"
