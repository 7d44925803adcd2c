"""The whole torch_sgm pipeline and its registration as a stereo backend."""
from __future__ import annotations

from importlib.metadata import entry_points

import numpy as np
import pluggy
import pytest
import torch
from pydantic import ValidationError

from core import hookspecs
from core.contracts import PluginContext, StereoBackend
from core.registry import Registry
from core.stereo_eval import score
from plugins.torch_sgm import plugin as torch_sgm_plugin
from plugins.torch_sgm import refine
from plugins.torch_sgm.pipeline import (TorchSGMParams, bgr_to_tensor, compute_disparity, cost_volume,
                                        right_view_map)
from plugins.torch_sgm.synthetic import fronto_parallel, layered_scene


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def test_fronto_parallel_pair_is_recovered_to_subpixel_accuracy():
    left, right, gt, nonocc = fronto_parallel(64, 96, 7.4, seed=2)
    disp, consistent = compute_disparity(left, right, 0, 24, TorchSGMParams(preset="seed"), device="cpu")
    inner = nonocc.copy()
    inner[:, :4] = inner[:, -4:] = inner[:4] = inner[-4:] = False
    err = np.abs(disp - gt)[inner]
    assert np.all(err < 0.5) and np.median(err) < 0.25
    assert consistent[inner].mean() > 0.97


def test_layered_scene_with_occlusions_scores_well():
    # Held out from any tuning on Middlebury: slanted planes, a depth edge, occlusions.
    left, right, gt, nonocc = layered_scene(seed=5)
    disp, consistent = compute_disparity(left, right, 0, 32, TorchSGMParams(preset="seed"), device="cpu")
    s = score(disp, gt, nonocc, consistent)
    assert s["dense"]["bad1.0"] < 12.0
    assert s["invalid"] == 0.0  # filling leaves a dense map
    assert s["coverage"] > 90.0


def test_chunked_cost_volume_equals_unchunked():
    left, right, _, _ = layered_scene(48, 64, seed=1)
    lt, rt = bgr_to_tensor(left, torch.device("cpu")), bgr_to_tensor(right, torch.device("cpu"))
    whole = cost_volume(lt, rt, list(range(20)), TorchSGMParams(preset="seed", chunk_disparities=64))
    chunked = cost_volume(lt, rt, list(range(20)), TorchSGMParams(preset="seed", chunk_disparities=3))
    assert torch.allclose(whole, chunked, atol=1e-6)


def test_output_respects_the_disparity_range_and_min_offset():
    left, right, gt, _ = fronto_parallel(40, 80, 12.0, seed=4)
    disp, _ = compute_disparity(left, right, 8, 20, TorchSGMParams(preset="seed"), device="cpu")
    assert disp.dtype == np.float32 and disp.shape == (40, 80)
    assert np.nanmin(disp) >= 8 and np.nanmax(disp) <= 20
    assert np.median(np.abs(disp - 12.0)) < 0.3


def test_without_filling_invalid_pixels_are_nan():
    left, right, gt, nonocc = layered_scene(seed=6)
    disp, consistent = compute_disparity(left, right, 0, 32, TorchSGMParams(preset="seed", fill="none"), device="cpu")
    assert np.array_equal(np.isfinite(disp), consistent)
    assert 0 < (~consistent).sum() < consistent.size * 0.3


@pytest.mark.parametrize("settings", [{}, {"two_view": True}, {"preset": "seed"}, {"align": "projective"},
                                      {"search": "full", "align": "none"}])
@pytest.mark.parametrize("shape", [(1, 1), (3, 40), (40, 3), (9, 9)])
def test_a_pair_of_any_size_gives_a_map_of_its_size(settings, shape):
    """A crop at a frame's corner can be a few pixels: the coarse pass pooled a pair of fewer rows than its
    factor to nothing, and the two views' neighbour shifts wrapped around a pair narrower than their reach."""
    left, right, _, _ = layered_scene(40, 40, seed=1)
    h, w = shape
    disp, consistent = compute_disparity(np.ascontiguousarray(left[:h, :w]), np.ascontiguousarray(right[:h, :w]),
                                         0, 4, TorchSGMParams(**settings), device="cpu")
    assert disp.shape == consistent.shape == shape
    assert np.all(np.isnan(disp) | ((disp >= 0) & (disp <= 4)))


def test_registered_through_the_hook_and_the_entry_point():
    manager = pluggy.PluginManager(hookspecs.PROJECT)
    manager.add_hookspecs(hookspecs)
    manager.register(torch_sgm_plugin)
    spec = Registry(manager).get("stereo", "torch_sgm").spec
    assert spec.settings_model is TorchSGMParams
    backend = spec.factory({"paths": 8}, PluginContext(device="cpu"))
    assert isinstance(backend, StereoBackend)
    left, right, _, _ = fronto_parallel(32, 48, 5.0)
    disp = backend.compute(left, right, 0, 16)
    assert disp.shape == (32, 48) and disp.dtype == np.float32
    names = {ep.name: ep.value for ep in entry_points(group=hookspecs.ENTRY_POINT_GROUP)}
    assert names.get("torch_sgm") == "plugins.torch_sgm.plugin"


def test_settings_reject_unknown_keys_and_bad_values():
    with pytest.raises(ValidationError):
        TorchSGMParams(preset="seed", p3=1.0)
    with pytest.raises(ValidationError):
        TorchSGMParams(preset="seed", paths=6)
    with pytest.raises(ValidationError, match="less than or equal to 10"):
        TorchSGMParams(median_radius=1000)  # its window stack asked for more memory than the machine has
    assert TorchSGMParams(preset="seed").model_dump()["w_census"] == 0.60


def test_auto_device_follows_the_engine_and_falls_back_to_cpu():
    backend = torch_sgm_plugin._factory({}, PluginContext(device="cpu"))
    assert backend.device.type == "cpu"
    backend = torch_sgm_plugin._factory({}, PluginContext(device="cuda"))
    assert backend.device.type == ("cuda" if torch.cuda.is_available() else "cpu")


class TestMatchingDevice:
    """``device: auto`` on a machine with CUDA: small pairs on the CPU, where a map is not thousands of kernel
    launches the GPU waits on; a device named by the recipe or the command is kept for every pair."""

    def test_a_small_pair_goes_to_the_cpu_a_large_one_stays_on_the_gpu(self):
        from plugins.torch_sgm.plugin import SMALL_ON_CPU_PIXELS, matching_device

        gpu = torch.device("cuda")
        assert matching_device(gpu, True, 94, 168).type == "cpu"  # the demo's frame at a quarter of the resolution
        assert matching_device(gpu, True, 376, 672).type == "cuda"  # a whole WVGA frame
        assert matching_device(gpu, True, 1, SMALL_ON_CPU_PIXELS).type == "cuda"
        assert matching_device(gpu, True, 1, SMALL_ON_CPU_PIXELS - 1).type == "cpu"
        assert matching_device(gpu, False, 94, 168).type == "cuda"
        assert matching_device(torch.device("cpu"), True, 376, 672).type == "cpu"

    @pytest.mark.parametrize("settings, ctx, small_on_cpu", [
        ({}, {"device": "cpu", "device_auto": True}, True),
        ({}, {"device": "cpu"}, False),  # the command named its device
        ({"device": "cpu"}, {"device": "cpu", "device_auto": True}, False),  # the recipe named it
    ])
    def test_only_a_device_nobody_named_moves_small_pairs(self, settings, ctx, small_on_cpu):
        assert torch_sgm_plugin._factory(settings, PluginContext(**ctx)).small_on_cpu is small_on_cpu

    def test_the_engine_says_when_its_device_was_auto(self, tmp_path, plane_sequence):
        from conftest import write_recipe

        from core import engine
        from core.recipe import load_recipe

        plane_sequence([0.0])
        text = ("name: t\ncamera: {plugin: replay, settings: {path: seq}}\nstereo: {backend: torch_sgm, "
                "max_disparity: 32}\ndetector: {plugin: yolov8}\noutputs: [{plugin: log}]\n")
        loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text))
        auto, named = engine.plugin_context(loaded, "auto"), engine.plugin_context(loaded, "cpu")
        assert auto.device_auto is True and auto.device in ("cpu", "cuda") and auto.recipe_dir == loaded.directory
        assert named.device_auto is False and named.device == "cpu"


def test_improved_preset_changes_defaults_but_explicit_settings_win():
    from plugins.torch_sgm.pipeline import IMPROVED

    improved = TorchSGMParams(preset="improved")
    assert IMPROVED and all(getattr(improved, k) == v for k, v in IMPROVED.items())
    assert improved != TorchSGMParams(preset="seed")
    key = next(iter(IMPROVED))
    assert getattr(TorchSGMParams(preset="improved", **{key: TorchSGMParams(preset="seed").model_dump()[key]}), key) \
        == TorchSGMParams(preset="seed").model_dump()[key]


def test_the_default_is_the_improved_preset():
    assert TorchSGMParams() == TorchSGMParams(preset="improved")
    assert TorchSGMParams(paths=4).paths == 4 and TorchSGMParams(paths=4).p2_edge == "path"  # the preset's, not the seed's


def test_improved_preset_beats_the_seed_on_a_held_out_synthetic_pair():
    # Not a Middlebury scene: guards the Middlebury-measured changes against overfitting.
    left, right, gt, nonocc = layered_scene(seed=11)
    seed = compute_disparity(left, right, 0, 32, TorchSGMParams(preset="seed"), device="cpu")
    improved = compute_disparity(left, right, 0, 32, TorchSGMParams(preset="improved"), device="cpu")
    seed_bad = score(seed[0], gt, nonocc, seed[1])["dense"]["bad1.0"]
    improved_bad = score(improved[0], gt, nonocc, improved[1])["dense"]["bad1.0"]
    assert improved_bad < 0.5 * seed_bad


def test_right_view_map_is_the_right_images_disparity():
    left, right, _, _ = fronto_parallel(48, 96, 7.4, seed=3)
    dev = torch.device("cpu")
    with torch.inference_mode():
        mirrored = right_view_map(bgr_to_tensor(left, dev), bgr_to_tensor(right, dev), 0, 24,
                                  TorchSGMParams(preset="improved"))
    inner = mirrored[0, 4:-4, 4:-12]  # the right image's last columns see beyond the left one
    assert mirrored.shape == (1, 48, 96) and (inner - 7.4).abs().median() < 0.25


def test_two_view_improves_held_out_synthetic_pairs_and_its_average_sharpens_the_choice():
    # Not Middlebury scenes: slanted planes, a depth edge and occlusions from the generator.
    dev = torch.device("cpu")
    preset = TorchSGMParams(preset="improved")
    for seed in (3, 5):
        left, right, gt, nonocc = layered_scene(seed=seed)
        alone, _ = compute_disparity(left, right, 0, 32, preset, device="cpu")
        both, _ = compute_disparity(left, right, 0, 32, TorchSGMParams(preset="improved", two_view=True),
                                    device="cpu")
        # the choice by itself, without the plane fits and the average that follow it in the pipeline
        with torch.inference_mode():
            right_map = right_view_map(bgr_to_tensor(left, dev), bgr_to_tensor(right, dev), 0, 32, preset)
            chosen = refine.two_view_choice(torch.from_numpy(alone)[None], right_map, preset.two_view_reach,
                                            preset.lr_tolerance, preset.two_view_iterations)[0].numpy()
        alone, chosen, both = (score(d, gt, nonocc)["dense"] for d in (alone, chosen, both))
        assert both["bad1.0"] < alone["bad1.0"]
        assert chosen["bad1.0"] < alone["bad1.0"]
        # the plane fits and the mean of the two views that follow the choice bring it closer to the truth
        assert both["bad0.5"] < chosen["bad0.5"] and both["avgerr"] < chosen["avgerr"]


def test_warm_up_reaches_every_compiled_kernel():
    """In a fresh process (where no kernel has run yet): after ``warm_up`` every numba kernel of the
    pipeline that the process's thread count runs has its machine code, so the first part does not pay for
    compiling one. One thread first, then two, in one process: a process for each took twice the time."""
    import json
    import subprocess
    import sys

    script = """
import json, numba, torch
from core.contracts import PluginContext
from plugins.torch_sgm import aggregate_numba, align_numba, cost_numba, planes_numba, refine_numba, select_numba, sgm_numba, linalg_numba
from plugins.torch_sgm.plugin import _factory
kernels = {f"{m.__name__}.{name}": k for m in (aggregate_numba, align_numba, cost_numba, planes_numba, refine_numba,
                                                  select_numba, sgm_numba, linalg_numba)
           for name, k in vars(m).items() if isinstance(k, numba.core.registry.CPUDispatcher)}
# called only from other kernels and compiled into them: the inlined ones, and these
inner = {"box_sums", "direct_box_sums", "_window_sums", "_guided"}
backend = _factory({}, PluginContext(device="cpu"))
missing = {}
for threads in (1, 2):
    torch.set_num_threads(threads)
    backend.warm_up()
    missing[threads] = sorted(n for n, k in kernels.items() if not k.signatures and k.targetoptions.get("inline") != "always"
                              and n.rsplit(".", 1)[1] not in inner)
print(json.dumps({"missing": missing, "count": len(kernels), "numba_threads": numba.config.NUMBA_NUM_THREADS}))
"""
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    seen = json.loads(result.stdout.strip().splitlines()[-1])
    assert seen["count"] >= 18, seen
    # SGM's paths across the rows: one kernel for one thread, another for more (numba runs no more threads than it has)
    parallel = "plugins.torch_sgm.sgm_numba._across_rows"
    if seen["numba_threads"] > 1:
        assert seen["missing"]["1"] == [parallel] and seen["missing"]["2"] == [], seen
    else:
        assert seen["missing"]["1"] == seen["missing"]["2"] == [parallel], seen


class TestStageClock:
    def test_each_stage_is_charged_its_own_time_in_the_order_first_run(self):
        from plugins.torch_sgm.stage_clock import StageClock

        ticks = iter([0.0, 1.0, 1.0, 3.5, 4.0, 4.25])
        clock = StageClock("cpu", clock=lambda: next(ticks))
        with clock("cost"):
            pass
        with clock("SGM"):
            pass
        with clock("cost"):
            pass
        assert list(clock.seconds) == ["cost", "SGM"] and clock.seconds == {"cost": 1.25, "SGM": 2.5}

    def test_a_stage_that_raises_is_still_charged(self):
        from plugins.torch_sgm.stage_clock import StageClock

        ticks = iter([0.0, 2.0])
        clock = StageClock("cpu", clock=lambda: next(ticks))
        with pytest.raises(RuntimeError):
            with clock("fit"):
                raise RuntimeError("no")
        assert clock.seconds == {"fit": 2.0}

    def test_the_timed_map_is_the_map(self):
        from plugins.torch_sgm.stage_clock import StageClock

        left, right, _, _ = layered_scene(40, 64, seed=3)
        params = TorchSGMParams(two_view=True)
        clock = StageClock("cpu")
        timed, _ = compute_disparity(left, right, 0, 24, params, "cpu", clock)
        plain, _ = compute_disparity(left, right, 0, 24, params, "cpu")
        assert np.array_equal(timed, plain, equal_nan=True)
        assert {"coarse pass", "vertical alignment", "cost and aggregation", "SGM", "winners", "slanted-plane filling",
                "weighted median", "local plane fit", "two views"} <= set(clock.seconds)
        assert all(s >= 0 for s in clock.seconds.values())
