"""torch_sgm on CUDA: the same code gives the same map as on the CPU.

These run only where torch sees a GPU (CI has none, so they skip there); they were run on an H200.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from core.contracts import PluginContext
from core.stereo_eval import score
from plugins.torch_sgm import plugin as torch_sgm_plugin
from plugins.torch_sgm.pipeline import TorchSGMParams, compute_disparity
from plugins.torch_sgm.synthetic import layered_scene

pytestmark = [pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
              pytest.mark.usefixtures("torch_one_thread")]

SETTINGS = {
    "seed": {"preset": "seed"},
    "seed-reference": {"preset": "seed", "implementation": "reference"},
    "improved": {"preset": "improved"},
    "improved-two-view": {"preset": "improved", "two_view": True},
    "improved-full-search": {"preset": "improved", "search": "full"},
}


@pytest.mark.parametrize("name", list(SETTINGS))
def test_cuda_map_matches_the_cpu_map(name):
    left, right, gt, nonocc = layered_scene(seed=5)
    params = TorchSGMParams(**SETTINGS[name])
    torch.cuda.reset_peak_memory_stats()
    on_gpu, ok_gpu = compute_disparity(left, right, 0, 32, params, device="cuda")
    assert torch.cuda.max_memory_allocated() > 0  # it really ran on the GPU
    on_cpu, ok_cpu = compute_disparity(left, right, 0, 32, params, device="cpu")
    assert on_gpu.dtype == np.float32 and on_gpu.shape == on_cpu.shape
    assert (ok_gpu == ok_cpu).mean() > 0.995
    # The two devices' maps are not bit-identical (docs/research-log.md, On CUDA before the Triton kernel): a few
    # pixels may differ.
    both = np.isfinite(on_gpu) & np.isfinite(on_cpu)
    assert (np.isfinite(on_gpu) == np.isfinite(on_cpu)).all()
    assert (np.abs(on_gpu - on_cpu)[both] > 0.05).mean() < 0.005
    gpu_bad, cpu_bad = (score(d, gt, nonocc)["dense"]["bad1.0"] for d in (on_gpu, on_cpu))
    assert abs(gpu_bad - cpu_bad) < 0.3


def test_cuda_is_used_when_the_recipe_or_engine_asks_for_it():
    assert torch_sgm_plugin._factory({"device": "cuda"}, PluginContext(device="cpu")).device.type == "cuda"
    assert torch_sgm_plugin._factory({}, PluginContext(device="cuda")).device.type == "cuda"
    assert torch_sgm_plugin._factory({}, PluginContext(device="cpu")).device.type == "cpu"


def test_auto_matches_small_pairs_on_the_cpu_and_a_named_cuda_every_pair_on_the_gpu():
    auto = torch_sgm_plugin._factory({}, PluginContext(device="cuda", device_auto=True))
    assert auto.device_for(48, 72).type == "cpu" and auto.device_for(376, 672).type == "cuda"
    for named in (torch_sgm_plugin._factory({}, PluginContext(device="cuda")),
                  torch_sgm_plugin._factory({"device": "cuda"}, PluginContext(device="cuda", device_auto=True))):
        assert named.device_for(48, 72).type == "cuda"
    left, right, _, _ = layered_scene(48, 72, seed=2)
    auto.warm_up()  # both devices
    assert np.isfinite(auto.compute(left, right, 0, 32)).any()


def test_stereo_command_on_cuda_reports_its_peak_gpu_memory(tmp_path):
    import cv2
    from click.testing import CliRunner

    from core.cli import _build

    left, right, _, _ = layered_scene(48, 72, seed=2)
    cv2.imwrite(str(tmp_path / "left.png"), left)
    cv2.imwrite(str(tmp_path / "right.png"), right)
    args = ["stereo", str(tmp_path / "left.png"), str(tmp_path / "right.png"), "--max-disp", "32"]
    result = CliRunner().invoke(_build(), args + ["--device", "cuda"])
    assert result.exit_code == 0, result.output
    peak = float(result.output.split("peak GPU memory ")[1].split(" MiB")[0])
    assert peak > 0
    on_cpu = CliRunner().invoke(_build(), args + ["--device", "cpu"])
    assert on_cpu.exit_code == 0 and "GPU" not in on_cpu.output
