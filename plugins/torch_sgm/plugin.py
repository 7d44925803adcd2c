"""Registers ``torch_sgm`` as a stereo backend."""
from __future__ import annotations

import numpy as np

from core.contracts import PluginContext, PluginSpec
from core.hookspecs import hookimpl
from plugins.torch_sgm.params import TorchSGMParams


BYTES_PER_CELL = 24  # the most measured (21 bytes per pixel and disparity) with room to spare
# Below this many pixels ``device: auto`` matches a pair on the CPU even where it found CUDA: a map is
# thousands of small kernel launches that a GPU waits on whatever the image's size. On an H200 the demo's
# crops took 59.5 ms a frame on CUDA (7.2 ms on two CPU cores of the development machine), a whole WVGA
# frame 146 ms (217-299 ms on those two cores): the GPU pays from about a third of a WVGA frame.
SMALL_ON_CPU_PIXELS = 100_000


def matching_device(device, small_on_cpu: bool, height: int, width: int):
    """The torch device a ``height`` x ``width`` pair is matched on: ``device``, or the CPU where
    ``small_on_cpu`` and the pair has fewer than SMALL_ON_CPU_PIXELS pixels while ``device`` is a GPU."""
    import torch

    if small_on_cpu and device.type == "cuda" and height * width < SMALL_ON_CPU_PIXELS:
        return torch.device("cpu")
    return device


class TorchSGM:
    def __init__(self, params: TorchSGMParams, device: str, small_on_cpu: bool = False):
        """``small_on_cpu``: pairs under SMALL_ON_CPU_PIXELS on the CPU where ``device`` is CUDA
        (``matching_device``; what ``device: auto`` does)."""
        from plugins.torch_sgm.pipeline import pick_device  # torch loads only when the backend is used

        self.params = params
        self.device = pick_device(device)
        self.small_on_cpu = small_on_cpu
        self.devices_used: set = set()  # what the maps ran on, for a benchmark to say

    def device_for(self, height: int, width: int):
        """The torch device a pair of this size is matched on."""
        return matching_device(self.device, self.small_on_cpu, height, width)

    def _map_device(self, image: np.ndarray):
        """``device_for`` the pair of which ``image`` is one, noted in ``devices_used``."""
        device = self.device_for(*image.shape[:2])
        self.devices_used.add(device.type)
        return device

    def compute(self, left: np.ndarray, right: np.ndarray, min_disp: float, max_disp: float) -> np.ndarray:
        return self.compute_with_mask(left, right, min_disp, max_disp)[0]

    def warm_up(self, helper: bool = True) -> None:
        """Match a small synthetic scene (matches, an occlusion, holes to fill) on every device this backend
        may match on, so that every stage's kernels are compiled, or loaded from numba's cache, before the
        first part. Where the cache lacks them (and ``helper``, on a machine of two cores or more), a second
        process compiles the later stages' kernels and depth's meanwhile (``kernel_warm_up``), and this waits
        for it."""
        import os

        import torch

        from plugins.torch_sgm import kernel_warm_up
        from plugins.torch_sgm.pipeline import compute_disparity
        from plugins.torch_sgm.synthetic import layered_scene

        settings = self.params.model_dump(mode="json")
        started = (kernel_warm_up.start("later", settings, (torch.get_num_threads(),))
                   if helper and (os.cpu_count() or 1) > 1 and kernel_warm_up.cold(settings) else None)
        try:
            left, right, _, _ = layered_scene()
            for device in {self.device, self.device_for(*left.shape[:2])}:
                compute_disparity(left, right, 0.0, 24.0, self.params, device)
        except BaseException:  # a stop (Ctrl-C, SIGTERM) or a failure here: the helper's kernels are not awaited
            if started is not None:
                kernel_warm_up.finish(started, timeout_s=0)
            raise
        if started is not None:
            kernel_warm_up.finish(started)

    def memory_bytes(self, height: int, width: int, disparities: int) -> int:
        """Host memory one map takes at most: on the CPU the cost volume, the SGM sums and the stages'
        temporaries, measured at 18-21 bytes per pixel and disparity where the whole range is searched
        (WVGA and 1344x752, 128 and 256 disparities, with and without ``two_view``); on CUDA the images and
        maps alone (the GPU's own memory runs out as an exception, not a killed process)."""
        if self.device_for(height, width).type == "cuda":
            return 64 * height * width
        return BYTES_PER_CELL * height * width * disparities

    def compute_timed(self, left, right, min_disp, max_disp) -> tuple[np.ndarray, dict[str, float]]:
        """``compute`` and the seconds each stage of the pipeline took (``inspect stereo --stages``)."""
        from plugins.torch_sgm.pipeline import compute_disparity
        from plugins.torch_sgm.stage_clock import StageClock

        device = self._map_device(left)
        clock = StageClock(device)
        disp, _ = compute_disparity(left, right, min_disp, max_disp, self.params, device, clock)
        return disp, clock.seconds

    def compute_with_mask(self, left, right, min_disp, max_disp) -> tuple[np.ndarray, np.ndarray]:
        """The disparity and the pixels that passed the left-right check (before hole filling);
        the evaluation scores the latter as the sparse result."""
        from plugins.torch_sgm.pipeline import compute_disparity

        return compute_disparity(left, right, min_disp, max_disp, self.params, self._map_device(left))


def _factory(settings: dict, ctx: PluginContext) -> TorchSGM:
    params = TorchSGMParams(**settings)
    # The recipe's setting wins; "auto" defers to the engine's device, then to what is available, and where
    # neither named the device it matches small pairs on the CPU (SMALL_ON_CPU_PIXELS)
    device = params.device if params.device != "auto" else (ctx.device if ctx.device in ("cpu", "cuda") else "auto")
    if device == "cuda":
        import torch
        if not torch.cuda.is_available() and params.device == "auto":
            device = "cpu"
    return TorchSGM(params, device, small_on_cpu=params.device == "auto" and ctx.device_auto)


@hookimpl
def stereo_inspect_stereo_backends() -> list[PluginSpec]:
    return [
        PluginSpec(
            name="torch_sgm",
            kind="stereo",
            factory=_factory,
            settings_model=TorchSGMParams,
            description="Classical census/AD/gradient cost + guided filter + SGM in PyTorch (CPU or CUDA)",
        )
    ]
