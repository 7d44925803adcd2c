"""Stereo backend ``opencv_sgbm``: OpenCV's StereoSGBM, the baseline the others are measured against."""
from __future__ import annotations

import math

import cv2
import numpy as np
from pydantic import Field

from core.contracts import PluginContext, PluginSpec
from core.hookspecs import hookimpl
from core.settings_model import Settings


class SGBMSettings(Settings):
    block_size: int = Field(5, ge=1, le=21)
    # the bounds keep OpenCV's C ints: beyond them every frame's stereo failed at run time, not in validate
    p1_per_channel: int = Field(8, ge=0, le=100_000, description="P1 = p1_per_channel * 3 * block_size^2")
    p2_per_channel: int = Field(32, ge=0, le=100_000, description="P2 = p2_per_channel * 3 * block_size^2")
    disp12_max_diff: int = Field(1, ge=-1, le=100_000, description="-1: no left-right check")
    uniqueness_ratio: int = Field(10, ge=0, le=100)
    speckle_window_size: int = Field(100, ge=0, le=1_000_000)
    speckle_range: int = Field(2, ge=0, le=100_000)
    mode: str = Field("sgbm", pattern="^(sgbm|hh|sgbm_3way|hh4)$")


_MODES = {
    "sgbm": cv2.STEREO_SGBM_MODE_SGBM,
    "hh": cv2.STEREO_SGBM_MODE_HH,
    "sgbm_3way": cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    "hh4": cv2.STEREO_SGBM_MODE_HH4,
}


class OpenCVSGBM:
    def __init__(self, settings: SGBMSettings):
        self.settings = settings

    def memory_bytes(self, height: int, width: int, disparities: int) -> int:
        """The most one map takes: the full-image modes (hh, hh4) keep a cost per pixel and disparity
        (3.6 bytes measured at 1344x752 with 128), the others a few rows of them."""
        disparities = max(16, -(-disparities // 16) * 16)  # OpenCV's multiple of 16
        if self.settings.mode in ("hh", "hh4"):
            return 4 * height * width * disparities + 16 * height * width
        return 32 * width * disparities + 16 * height * width

    def compute(self, left: np.ndarray, right: np.ndarray, min_disp: float, max_disp: float) -> np.ndarray:
        s = self.settings
        lo = math.floor(min_disp)
        # OpenCV wants the search width as a positive multiple of 16.
        num = max(16, int(math.ceil((max_disp - lo) / 16.0)) * 16)
        narrowest = lo + num + s.block_size // 2 + 1  # below it OpenCV fails an assertion in C++
        if left.shape[1] < narrowest:
            raise ValueError(f"the pair is {left.shape[1]} px wide; searching disparities {lo}..{lo + num - 1} "
                             f"(a multiple of 16) with block_size {s.block_size} needs {narrowest} px at least")
        area = 3 * s.block_size * s.block_size
        matcher = cv2.StereoSGBM_create(
            minDisparity=lo,
            numDisparities=num,
            blockSize=s.block_size,
            P1=s.p1_per_channel * area,
            P2=s.p2_per_channel * area,
            disp12MaxDiff=s.disp12_max_diff,
            uniquenessRatio=s.uniqueness_ratio,
            speckleWindowSize=s.speckle_window_size,
            speckleRange=s.speckle_range,
            mode=_MODES[s.mode],
        )
        raw = matcher.compute(left, right)  # int16 fixed point, 4 fractional bits
        disparity = raw.astype(np.float32) / 16.0
        # Invalid pixels come back as (minDisparity - 1) * 16.
        disparity[raw <= (lo - 1) * 16] = np.nan
        disparity[(disparity < min_disp) | (disparity >= max_disp)] = np.nan
        return disparity


def _factory(settings: dict, ctx: PluginContext) -> OpenCVSGBM:
    return OpenCVSGBM(SGBMSettings(**settings))


@hookimpl
def stereo_inspect_stereo_backends() -> list[PluginSpec]:
    return [
        PluginSpec(
            name="opencv_sgbm",
            kind="stereo",
            factory=_factory,
            settings_model=SGBMSettings,
            description="OpenCV StereoSGBM (baseline), sub-pixel, invalid = NaN",
        )
    ]
