"""Registers ``torch_sgm`` as a stereo backend."""
from __future__ import annotations

import numpy as np

from core.contracts import PluginContext, PluginSpec
from core.hookspecs import hookimpl
from plugins.torch_sgm.params import TorchSGMParams


BYTES_PER_CELL = 24  # the most measured (21 bytes per pixel and disparity) with room to spare


class TorchSGM:
    def __init__(self, params: TorchSGMParams, device: str):
        from plugins.torch_sgm.pipeline import pick_device  # torch loads only when the backend is used

        self.params = params
        self.device = pick_device(device)

    def compute(self, left: np.ndarray, right: np.ndarray, min_disp: float, max_disp: float) -> np.ndarray:
        return self.compute_with_mask(left, right, min_disp, max_disp)[0]

    def warm_up(self) -> None:
        """Match a small synthetic scene (matches, an occlusion, holes to fill) so that every stage's
        kernels are compiled, or loaded from numba's cache, before the first part."""
        from plugins.torch_sgm.synthetic import layered_scene

        left, right, _, _ = layered_scene()
        self.compute(left, right, 0.0, 24.0)

    def memory_bytes(self, height: int, width: int, disparities: int) -> int:
        """Host memory one map takes at most: on the CPU the cost volume, the SGM sums and the stages'
        temporaries, measured at 18-21 bytes per pixel and disparity where the whole range is searched
        (WVGA and 1344x752, 128 and 256 disparities, with and without ``two_view``); on CUDA the images and
        maps alone (the GPU's own memory runs out as an exception, not a killed process)."""
        if str(self.device).startswith("cuda"):
            return 64 * height * width
        return BYTES_PER_CELL * height * width * disparities

    def compute_timed(self, left, right, min_disp, max_disp) -> tuple[np.ndarray, dict[str, float]]:
        """``compute`` and the seconds each stage of the pipeline took (``inspect stereo --stages``)."""
        from plugins.torch_sgm.pipeline import compute_disparity
        from plugins.torch_sgm.stage_clock import StageClock

        clock = StageClock(self.device)
        disp, _ = compute_disparity(left, right, min_disp, max_disp, self.params, self.device, clock)
        return disp, clock.seconds

    def compute_with_mask(self, left, right, min_disp, max_disp) -> tuple[np.ndarray, np.ndarray]:
        """The disparity and the pixels that passed the left-right check (before hole filling);
        the evaluation scores the latter as the sparse result."""
        from plugins.torch_sgm.pipeline import compute_disparity

        return compute_disparity(left, right, min_disp, max_disp, self.params, self.device)


def _factory(settings: dict, ctx: PluginContext) -> TorchSGM:
    params = TorchSGMParams(**settings)
    # The recipe's setting wins; "auto" defers to the engine's device, then to what is available.
    device = params.device if params.device != "auto" else (ctx.device if ctx.device in ("cpu", "cuda") else "auto")
    if device == "cuda":
        import torch
        if not torch.cuda.is_available() and params.device == "auto":
            device = "cpu"
    return TorchSGM(params, device)


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
