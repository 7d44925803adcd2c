"""A stereo stage that cannot fit in memory is refused (before the run, or as its part's ERROR) instead of
the process being killed by the kernel with rejects queued (``core.stereo_memory``)."""
from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest
import stereo_inspect_fixed_roi
from conftest import ROOT, cli_here, png_declaring, write_recipe
from test_engine import RECIPE

from core import engine, stereo_memory
from core.recipe import load_recipe
from core.recipe.schema import StereoSection
from core.registry import Registry, make_manager
from core.types import Calibration, Status
from plugins.opencv_sgbm import OpenCVSGBM, SGBMSettings
from plugins.torch_sgm.params import TorchSGMParams
from plugins.torch_sgm.plugin import TorchSGM

GIB = 2**30
WVGA = Calibration(focal_px=350.06, baseline_mm=120.0, cx=335.5, cy=187.5, width=672, height=376)


class NoEstimate:
    """A third-party backend that states nothing about its memory."""

    def compute(self, left, right, min_disp, max_disp):
        raise AssertionError("not called")


class TestMemoryProblem:
    def test_a_map_that_fits_is_no_problem_one_that_does_not_is_named_with_its_size(self):
        backend = TorchSGM(TorchSGMParams(), "cpu")
        needed = stereo_memory.needed_bytes(backend, 376, 672, 128)
        assert needed == 24 * 376 * 672 * 128
        assert stereo_memory.memory_problem(backend, 376, 672, 128, available=needed) is None
        problem = stereo_memory.memory_problem(backend, 376, 672, 128, available=needed // 2, name="torch_sgm")
        assert problem.startswith("torch_sgm would need 0.7 GiB for a 672x376 image with 128 disparities")

    def test_a_backend_that_states_nothing_is_not_refused(self):
        assert stereo_memory.memory_problem(NoEstimate(), 10_000, 10_000, 10_000, available=1) is None

    def test_opencv_full_image_modes_hold_a_cost_per_pixel_and_disparity_the_others_rows(self):
        hh = stereo_memory.needed_bytes(OpenCVSGBM(SGBMSettings(mode="hh")), 752, 1344, 128)
        rows = stereo_memory.needed_bytes(OpenCVSGBM(SGBMSettings(mode="sgbm")), 752, 1344, 128)
        assert hh > 4 * 752 * 1344 * 128 > 20 * rows


class TestWholeFrameProblem:
    def test_half_the_scale_needs_an_eighth(self):
        backend = TorchSGM(TorchSGMParams(), "cpu")
        full = StereoSection(working_distance_mm=(300, 700), scale=1.0)
        half = full.model_copy(update={"scale": 0.5})
        lo, hi = full.search_range(WVGA)
        needed = stereo_memory.needed_bytes(backend, 376, 672 - int(lo), stereo_memory.search_disparities(lo, hi))
        assert stereo_memory.whole_frame_problem(full, backend, WVGA, available=needed) is None
        problem = stereo_memory.whole_frame_problem(full, backend, WVGA, available=needed - 1)
        assert "torch_sgm would need" in problem and "stereo.scale 1" in problem and "stereo.scale" in problem
        assert stereo_memory.whole_frame_problem(half, backend, WVGA, available=needed // 7) is None
        assert stereo_memory.whole_frame_problem(half, backend, WVGA, available=needed // 9) is not None


MEASURE = """
import json, threading, time
import numpy as np
import psutil
import torch
from plugins.torch_sgm.params import TorchSGMParams
from plugins.torch_sgm.plugin import TorchSGM
torch.set_num_threads(1)
rng = np.random.default_rng(0)
left = (rng.random((376, 672, 3)) * 255).astype(np.uint8)
right = np.roll(left, -40, axis=1)
backend = TorchSGM(TorchSGMParams(search="full", align="none"), "cpu")
backend.compute(left[:64, :128].copy(), right[:64, :128].copy(), 0.0, 16.0)  # kernels compiled first
process, peak, done = psutil.Process(), [0], threading.Event()
def watch():
    while not done.is_set():
        peak[0] = max(peak[0], process.memory_info().rss)
        time.sleep(0.002)
before = process.memory_info().rss
watcher = threading.Thread(target=watch)
watcher.start()
backend.compute(left, right, 0.0, 128.0)
done.set()
watcher.join()
print(json.dumps({"taken": peak[0] - before, "stated": backend.memory_bytes(376, 672, 128)}))
"""


def test_torch_sgm_states_at_least_what_a_whole_range_search_takes():
    """Measured in a process of its own: the most resident memory one WVGA map over 128 disparities adds (a
    process's lifetime peak would be that of compiling the kernels)."""
    out = subprocess.run([sys.executable, "-c", MEASURE], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert out.returncode == 0, out.stderr
    figures = json.loads(out.stdout.strip().splitlines()[-1])
    assert 0.5 * figures["stated"] < figures["taken"] <= figures["stated"]


@pytest.fixture
def registry():
    return Registry(make_manager((stereo_inspect_fixed_roi,)))


def _loaded(tmp_path, registry, info, region):
    schedule = "every_frame" if region == "full" else "on_defect"
    text = RECIPE.format(box=info["box"], output="log").replace(
        "  schedule: every_frame", f"  region: {region}\n  schedule: {schedule}")
    path = write_recipe(tmp_path / "r.yaml", text)
    return load_recipe(path, registry=registry)


class TestEngine:
    def test_whole_frames_that_cannot_fit_are_refused_before_the_run(self, tmp_path, plane_sequence, registry,
                                                                     monkeypatch):
        loaded = _loaded(tmp_path, registry, plane_sequence([0.0]), "full")
        monkeypatch.setattr(stereo_memory, "available_bytes", lambda: 64 * 2**10)
        with pytest.raises(engine.SetupError, match=r"r\.yaml:\d+: stereo: opencv_sgbm would need .* GiB"):
            engine.run(loaded, registry=registry, device="cpu")
        assert not (tmp_path / "results").exists()  # refused before a run was recorded

    def test_a_crop_that_cannot_fit_is_its_parts_error_and_the_run_goes_on(self, tmp_path, plane_sequence, registry,
                                                                          monkeypatch):
        loaded = _loaded(tmp_path, registry, plane_sequence([0.0, 2.0]), "defects")
        monkeypatch.setattr(stereo_memory, "available_bytes", lambda: 64 * 2**10)
        seen = []
        summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
        assert summary.frames == 2 and [o.part.verdict.status for o in seen] == [Status.ERROR, Status.ERROR]
        assert all("would need" in o.part.verdict.reasons[0] for o in seen)


def _big_sequence(tmp_path):
    """The demo sequence with a calibration that states a frame 40 times as large each way, its first pair black
    images of that size (whose headers the recipe's check reads; no check here decodes them)."""
    seq = tmp_path / "big"
    shutil.copytree(ROOT / "sim_fixtures" / "steel_plate", seq)
    calib = seq / "calib.yaml"
    lines = []
    for line in calib.read_text().splitlines():
        key, _, value = line.partition(": ")
        lines.append(f"{key}: {float(value) * 40:g}" if key in ("focal_px", "cx", "cy", "width", "height") else line)
    calib.write_text("\n".join(lines) + "\n")
    for eye in ("left", "right"):
        (seq / eye / "000000.jpg").unlink()
        (seq / eye / "000000.png").write_bytes(png_declaring(672 * 40, 376 * 40))
    return seq


def test_validate_refuses_whole_frames_that_cannot_fit_and_warns_for_crops(tmp_path):
    seq = _big_sequence(tmp_path)
    demo = str(ROOT / "recipes" / "steel_plate.yaml")
    full = cli_here("validate", demo, "--set", f"camera.settings.path={seq}", "--set", "stereo.region=full",
               "--set", "stereo.schedule=every_frame")
    lines = [line for line in full.stderr.splitlines() if line.strip()]
    assert full.returncode == 2 and len(lines) == 1 and "stereo: torch_sgm would need" in lines[0], full.stderr
    assert "GiB of memory is available" in lines[0] and "stereo.scale" in lines[0]
    crops = cli_here("validate", demo, "--set", f"camera.settings.path={seq}")
    assert crops.returncode == 0 and "a box covering most of the frame would be its part's ERROR" in crops.stderr
    run = cli_here("run", demo, "--set", f"camera.settings.path={seq}", "--set", "stereo.region=full",
              "--set", "stereo.schedule=every_frame", "--set", f"results.path={tmp_path / 'results'}",
              "--set", "outputs=[{plugin: log}]")
    assert run.returncode == 2 and "torch_sgm would need" in run.stderr
    assert not (tmp_path / "results").exists()
