from __future__ import annotations

import json

import pytest

from conftest import ROOT, cli, cli_here

from core.bench import add_own_share, live_markdown


def test_bench_times_every_stage_and_saves_tables(tmp_path):
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "opencv_sgbm",
              "--regions", "full", "--frames", "2", "--repeats", "2", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "bench-wvga-cpu.json").read_text())
    result = report["results"][0]
    assert result["backend"] == "opencv_sgbm" and result["frames"] == 2 and result["repeats"] == 2
    assert result["region"] == "full" and "depth_vs_full_frame" not in result
    stages = result["stages_ms"]
    assert set(stages) == {"capture", "detection", "stereo", "depth", "decision", "outputs", "loop"}
    assert all(s["min"] <= s["median"] <= s["max"] for s in stages.values())
    parts = sum(stages[k]["median"] for k in stages if k != "loop")
    assert abs(parts - stages["loop"]["median"]) < 0.05 * stages["loop"]["median"] + 1.0
    assert stages["stereo"]["median"] > 0 and result["fps"] > 0 and result["peak_rss_mb"] > 0
    ratio = (stages["stereo"]["median"] + stages["depth"]["median"]) / stages["detection"]["median"]
    assert result["stereo_and_depth_over_detection"] == ratio
    assert report["machine"]["cores"] >= 1 and report["resolution"] == "672x376"
    assert "| opencv_sgbm |" in (tmp_path / "bench-wvga-cpu.md").read_text()


def test_bench_at_another_zed_mode_and_unknown_backend(tmp_path):
    out = cli_here("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "nope", "--out", str(tmp_path))
    assert out.returncode == 2 and "unknown stereo backend nope" in out.stderr
    out = cli_here("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", " ,", "--out", str(tmp_path))
    assert out.returncode == 2 and "--backends: give at least one of" in out.stderr
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "opencv_sgbm",
              "--resolution", "2k", "--regions", "full", "--frames", "1", "--repeats", "1", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    assert json.loads((tmp_path / "bench-2k-cpu.json").read_text())["resolution"] == "2208x1242"


def test_bench_defect_region_is_compared_with_full_frame_and_detection_alone(tmp_path):
    """Frames 1-2 of the sim sequence hold defects the detector finds; the defects row measures them on
    crops and states how far that depth is from full-frame depth; "none" times detection alone."""
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "none,opencv_sgbm",
              "--regions", "defects", "--frames", "3", "--repeats", "1", "--threads", "1", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    results = json.loads((tmp_path / "bench-wvga-cpu.json").read_text())["results"]
    assert [(r["backend"], r["region"]) for r in results] == [("none", "-"), ("opencv_sgbm", "defects")]
    assert results[0]["stages_ms"]["stereo"]["median"] == 0.0 and results[0]["stages_ms"]["detection"]["median"] > 0
    assert results[0]["stereo_and_depth_over_detection"] is None and results[1]["stereo_and_depth_over_detection"] > 0
    versus = results[1]["depth_vs_full_frame"]
    assert versus["defects"] >= 1 and versus["availability_differs"] == 0
    # what the surface fit is added to, timed apart: the backend's plane and median alone, a part of depth's time
    assert "plane_and_median_ms" not in results[0]
    assert 0 < results[1]["plane_and_median_ms"] < results[1]["stages_ms"]["depth"]["median"]
    assert versus["distance_mm"] < 0.05 and versus["deviation_mm"] < 0.05
    assert "| opencv_sgbm | defects |" in (tmp_path / "bench-wvga-cpu.md").read_text()


def test_a_backend_that_matched_on_another_device_than_the_bench_s_says_so():
    """torch_sgm's device auto matches small pairs on the CPU on a GPU machine: the table must not credit
    the GPU with them."""
    from core.bench import STAGES, markdown

    stages = {s: {"median": 1.0, "min": 1.0, "max": 1.0} for s in STAGES}
    row = {"region": "defects", "stages_ms": stages, "fps": 10.0, "peak_rss_mb": 100.0,
           "stereo_and_depth_over_detection": 0.5}
    report = {"recipe": "r.yaml", "resolution": "672x376", "device": "cuda", "when": "now",
              "machine": {"cpu": "x", "cores": 16, "torch_threads": 8, "gpu": "H200"},
              "results": [{**row, "backend": "torch_sgm", "stereo_devices": ["cpu"]},
                          {**row, "backend": "torch_sgm", "region": "full", "stereo_devices": ["cuda"]},
                          {**row, "backend": "opencv_sgbm"}]}
    table = markdown(report)
    assert "| torch_sgm (matched on cpu) | defects |" in table
    assert "| torch_sgm | full |" in table and "| opencv_sgbm | defects |" in table


def test_torch_sgm_says_where_it_matched(tmp_path):
    out = cli("bench", "--backends", "torch_sgm", "--regions", "defects", "--frames", "2", "--repeats", "1",
              "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    result = json.loads((tmp_path / "bench-wvga-cpu.json").read_text())["results"][0]
    assert result["stereo_devices"] == ["cpu"]


def test_bench_versus_compares_depth_with_other_settings_of_the_backend(tmp_path):
    """torch_sgm's coarse-to-fine search against its full search: the same depth for each defect found
    on frames 1-2 (the first frame is sound plate)."""
    recipe = str(ROOT / "recipes" / "steel_plate.yaml")
    out = cli("bench", "--recipe", recipe, "--backends", "torch_sgm", "--regions", "defects", "--frames", "3",
              "--repeats", "1", "--threads", "1", "--set", "stereo.backend=torch_sgm",
              "--set", "stereo.settings.search=coarse_to_fine", "--versus", "search=full", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    result = json.loads((tmp_path / "bench-wvga-cpu.json").read_text())["results"][0]
    assert result["versus"] == {"search": "full"}
    versus = result["depth_vs_full_frame"]
    assert versus["defects"] >= 2 and versus["availability_differs"] == 0
    assert versus["distance_mm"] < 0.05 and versus["deviation_mm"] < 0.05
    assert "depth vs full frame with search=full" in (tmp_path / "bench-wvga-cpu.md").read_text()
    bad = cli_here("bench", "--recipe", recipe, "--backends", "opencv_sgbm", "--set", "stereo.backend=opencv_sgbm",
              "--versus", "search=full", "--out", str(tmp_path))
    assert bad.returncode == 2 and "--versus: search: Extra inputs are not permitted" in bad.stderr
    bad = cli_here("bench", "--recipe", recipe, "--backends", "none", "--versus", "search=full", "--out", str(tmp_path))
    assert bad.returncode == 2 and "which --backends leaves out" in bad.stderr
    bad = cli_here("bench", "--recipe", recipe, "--backends", "torch_sgm", "--set", "stereo.backend=torch_sgm",
              "--versus", "search=sideways", "--out", str(tmp_path))
    assert bad.returncode == 2 and "--versus: search:" in bad.stderr
    for value, says in (("[", "--versus: fit_radius: Input should be a valid integer"),  # was a YAML traceback
                        ("010", "--versus fit_radius=010: 010: YAML reads a leading zero as octal, 8")):
        bad = cli_here("bench", "--recipe", recipe, "--backends", "torch_sgm", "--set", "stereo.backend=torch_sgm",
                       "--versus", f"fit_radius={value}", "--out", str(tmp_path))
        assert bad.returncode == 2 and says in bad.stderr and "Traceback" not in bad.stderr, bad.stderr


def test_soak_reports_rss_at_start_and_end(tmp_path):
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--soak", "12", "--soak-every", "5",
              "--threads", "1", "--set", "stereo.region=defects", "--set", "threads=2", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    report = json.loads((tmp_path / "soak.json").read_text())
    assert report["machine"]["torch_threads"] == 1  # --threads wins over the recipe's, in the real loop too
    assert report["frames"] == 12  # the 10-frame sequence looped
    assert [n for n, _ in report["rss_mb"]] == [1, 5, 10, 12]
    assert 0 < report["rss_start_mb"] <= report["peak_rss_mb"] and report["rss_end_mb"] <= report["peak_rss_mb"]
    assert "RSS" in out.stdout and not (ROOT / "results" / "steel_plate" / "soak").exists()


def test_live_runs_the_real_loop_alone_with_the_matchers_depth_and_with_the_recipes_in_reversed_rounds(tmp_path):
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "none", "--repeats", "1",
              "--frames", "1", "--live", "6", "--live-rounds", "2", "--threads", "1", "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    live = json.loads((tmp_path / "bench-wvga-cpu.json").read_text())["live"]
    alone, depth = live["rows"]["detection alone"], live["rows"]["with depth"]
    matcher = live["rows"]["the matcher's depth"]
    assert live["concurrent"] is True and alone["frames"] == depth["frames"] == matcher["frames"] == 6
    # the second round runs the loops in reverse, so that a steady drift falls on all alike
    assert live["order"] == ["detection alone", "the matcher's depth", "with depth", "with depth",
                             "the matcher's depth", "detection alone"]
    # nothing measured; the images of each part without defects are checked to show the plate in range
    assert set(alone["mean_ms"]) == {"detection", "plate check"} and alone["counts"] == {"PASS": 12}
    assert {"detection", "stereo", "depth"} <= set(depth["mean_ms"]) and depth["counts"].get("REJECT", 0) > 0
    assert len(alone["fps_rounds"]) == len(depth["fps_rounds"]) == 2
    assert alone["fps"] == pytest.approx(sum(alone["fps_rounds"]) / 2)  # the median of two
    assert live["ratios"] == [d / a for a, d in zip(alone["fps_rounds"], depth["fps_rounds"])]
    assert live["ratio"] == pytest.approx(sum(live["ratios"]) / 2) and live["ratio"] > 0
    assert "with depth ÷ detection alone" in out.stdout and "round by round" in out.stdout
    # what the surface fit costs the loop as it runs: the recipe's rate over the matcher's, round by round
    assert live["fit_ratios"] == [d / m for m, d in zip(matcher["fps_rounds"], depth["fps_rounds"])]
    assert live["fit_ratio"] == pytest.approx(sum(live["fit_ratios"]) / 2) and live["fit_ratio"] > 0
    assert f"with depth ÷ the matcher's depth: {live['fit_ratio']:.2f}" in out.stdout
    # depth's share of a frame: its mean time a part over the frame time at the loop's rate
    assert live["depth_share"] == pytest.approx(depth["mean_ms"]["depth"] * depth["fps"] / 1000.0)
    assert 0 < live["depth_share"] < 1 and f"depth's share of a frame with depth: {live['depth_share']:.0%}" in out.stdout
    # the depth goal's measure: what the surface fit adds to the matcher's depth, over the same frame time
    assert {"detection", "stereo", "depth"} <= set(matcher["mean_ms"]) and 0 < matcher["mean_ms"]["depth"]
    assert live["added_share"] == pytest.approx((depth["mean_ms"]["depth"] - matcher["mean_ms"]["depth"])
                                                * depth["fps"] / 1000.0)
    assert live["added_share"] < live["depth_share"] and "the surface fit's share beyond the matcher's depth" in out.stdout
    assert not (ROOT / "results" / "steel_plate" / "live").exists()


def test_live_with_the_matchers_depth_as_the_recipes_runs_it_once(tmp_path):
    out = cli("bench", "--recipe", str(ROOT / "recipes" / "steel_plate.yaml"), "--backends", "none", "--repeats", "1",
              "--frames", "1", "--live", "2", "--live-rounds", "1", "--threads", "1", "--set", "depth.method=disparity",
              "--out", str(tmp_path))
    assert out.returncode == 0, out.stderr
    live = json.loads((tmp_path / "bench-wvga-cpu.json").read_text())["live"]
    assert live["order"] == ["detection alone", "with depth"] and live["added_share"] is None
    assert live["fit_ratios"] == [] and live["fit_ratio"] is None
    assert live["depth_share"] > 0 and "the matcher's depth" not in out.stdout


class TestAddOwnShare:
    REPORT = {"results": [{"backend": "none", "region": "-", "stages_ms": {"depth": {"median": 0.0}}},
                          {"backend": "torch_sgm", "region": "full", "stages_ms": {"depth": {"median": 30.0}},
                           "plane_and_median_ms": 1.0},
                          {"backend": "torch_sgm", "region": "defects", "stages_ms": {"depth": {"median": 20.0}},
                           "plane_and_median_ms": 1.0}]}

    def test_depth_s_share_less_the_plane_and_median_s_part_of_the_recipe_s_row(self):
        live = {"depth_share": 0.30}
        add_own_share(live, self.REPORT, "torch_sgm", "defects")
        assert live["plane_and_median_of_depth"] == pytest.approx(0.05)
        assert live["own_share"] == pytest.approx(0.30 * 0.95)
        assert "the surface fit's own work: 28% of a frame" in live_markdown(
            {"concurrent": True, "threads": "auto", "rounds": 1, "rows": {"with depth": {
                "frames": 1, "fps": 10.0, "fps_rounds": [10.0], "mean_ms": {"depth": 30.0}}}, "ratio": None, **live})

    def test_nothing_without_the_recipe_s_row_its_plane_and_median_or_depth(self):
        for backend, region, share in (("opencv_sgbm", "defects", 0.3), ("none", "-", 0.3),
                                       ("torch_sgm", "defects", None)):
            live = {"depth_share": share}
            add_own_share(live, self.REPORT, backend, region)
            assert "own_share" not in live


def test_live_rounds_without_live_is_refused(tmp_path):
    out = cli_here("bench", "--backends", "none", "--live-rounds", "2", "--out", str(tmp_path))
    assert out.returncode == 2 and out.stderr == "error: --live-rounds needs --live FRAMES\n"
    assert list(tmp_path.iterdir()) == []


def test_a_frame_that_cannot_be_read_is_one_line_naming_it(tmp_path):
    """Timings of a loop that skipped it would be of other frames than the table says: refused, not a traceback."""
    import shutil

    sequence = tmp_path / "seq"
    shutil.copytree(ROOT / "sim_fixtures" / "steel_plate", sequence)
    cut = sequence / "left" / "000001.jpg"
    cut.write_bytes(cut.read_bytes()[:500])
    out = cli("bench", "--sequence", str(sequence), "--backends", "none", "--repeats", "1", "--out", str(tmp_path / "o"))
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert out.stderr == f"error: {sequence}: {cut}: left image of frame 000001 is not whole: truncated JPEG (no " \
                         "end-of-image marker)\n"
    assert list((tmp_path / "o").iterdir()) == []  # no table of other frames


@pytest.mark.parametrize("mode", [[], ["--soak", "2"]])
def test_a_camera_that_cannot_open_is_one_line_naming_the_recipe_key(tmp_path, mode):
    sequence = tmp_path / "seq"
    (sequence / "left").mkdir(parents=True)
    (sequence / "right").mkdir()
    (sequence / "calib.yaml").write_text((ROOT / "sim_fixtures" / "steel_plate" / "calib.yaml").read_text())
    out = cli("bench", "--sequence", str(sequence), "--backends", "none", "--repeats", "1", *mode,
              "--out", str(tmp_path / "o"))
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert out.stderr == f"error: {ROOT / 'recipes' / 'steel_plate.yaml'}: camera: replay: {sequence}: no frames in left/\n"


class TestResizeFrame:
    """The bench times the ZED's modes: the demo's WVGA frames scaled to one, or a recording at it as it is."""

    def _frame(self, width, height):
        import numpy as np

        from core.types import Calibration, StereoFrame

        image = np.zeros((height, width, 3), np.uint8)
        calib = Calibration(350.06 * width / 672, 120.0, (width - 1) / 2, (height - 1) / 2, width, height, 0.0)
        return StereoFrame("000000", 0, image, image.copy(), calib, 0.0, "test")

    def test_every_zed_mode_is_offered(self):
        from core.bench import RESOLUTIONS

        assert RESOLUTIONS["hd1080"] == (1920, 1080) and RESOLUTIONS["2k"] == (2208, 1242)

    def test_a_recording_at_the_mode_is_timed_as_it_is(self):
        from core.bench import RESOLUTIONS, resize_frame

        frame = self._frame(2208, 1242)
        assert resize_frame(frame, RESOLUTIONS["2k"]) is frame

    def test_wvga_scaled_to_2k_keeps_its_geometry(self):
        from core.bench import RESOLUTIONS, resize_frame

        scaled = resize_frame(self._frame(672, 376), RESOLUTIONS["2k"])
        assert scaled.left.shape == (1242, 2208, 3) and scaled.right.shape == (1242, 2208, 3)
        assert scaled.calib.width == 2208 and abs(scaled.calib.focal_px - 350.06 * 2208 / 672) < 1e-9


def test_a_detector_that_fails_on_a_frame_is_a_one_line_error_naming_it(tmp_path):
    # timings of a loop that skipped the frame would be of other frames; it ended the bench in a traceback
    out = cli_here("bench", "--backends", "none", "--repeats", "1", "--frames", "3",
                   "--set", "detector.settings.max_det=1", "--out", str(tmp_path))
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert "frame 000001: detection failed: DetectionLimit: the detector reached its max_det of 1" in out.stderr
