"""Camera ``replay``: plays a recorded sequence folder as if it were the line camera.

It plays the synthetic sequences, folders written by ``inspect camera record``, and any
folder of ``left/``+``right/`` pairs with a ``calib.yaml`` (or one Middlebury scene).
A frame that is missing or corrupt becomes a ``FrameError``: the engine rejects that part.
"""
from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

from pydantic import Field, ValidationInfo, field_validator

from core.contracts import PluginContext, PluginSpec
from core.hookspecs import hookimpl
from core.settings_model import Settings
from core.types import Calibration, FrameError, StereoFrame
from drivers import sequence_folder as seq


MIN_RATE_FPS = 0.01  # a frame every 100 s


class ReplaySettings(Settings):
    path: str = Field(description="sequence folder; relative to the recipe file")
    rate_fps: float = Field(0.0, ge=0.0, le=1000.0,
                            description="frames per second; 0 plays as fast as the line consumes")
    loop: bool = False
    max_frames: int | None = Field(None, ge=1)

    @field_validator("rate_fps")
    @classmethod
    def _a_rate(cls, value: float) -> float:
        # 1e-300 fps: the wait for the second frame overflowed the clock, and the run stopped on it
        if 0.0 < value < MIN_RATE_FPS:
            raise ValueError(f"{value:g}: 0 (as fast as the line takes them) or at least {MIN_RATE_FPS:g} frames a "
                             f"second")
        return value

    @field_validator("path")
    @classmethod
    def _exists(cls, value: str, info: ValidationInfo) -> str:
        base = Path((info.context or {}).get("recipe_dir", "."))
        folder = Path(value).expanduser()
        folder = folder if folder.is_absolute() else (base / folder).resolve()
        if not folder.is_dir():
            raise ValueError(f"sequence folder not found: {folder}")
        # what the camera would fail on when it opens, said where the recipe names the folder
        try:
            problem = seq.first_frame_problem(folder, seq.read_calibration(folder))
        except seq.SequenceError as exc:
            raise ValueError(str(exc)) from None
        if problem is not None:
            raise ValueError(problem)
        return str(folder)


def calibration_from_dict(data: dict) -> Calibration:
    return Calibration(
        focal_px=float(data["focal_px"]),
        baseline_mm=float(data["baseline_mm"]),
        cx=float(data["cx"]),
        cy=float(data["cy"]),
        width=int(data["width"]),
        height=int(data["height"]),
        doffs=float(data.get("doffs", 0.0)),
    )


class ReplayCamera:
    def __init__(self, settings: ReplaySettings):
        self.settings = settings
        self.folder = Path(settings.path)
        self.calib = calibration_from_dict(seq.read_calibration(self.folder))
        self.files = seq.list_frames(self.folder)
        if not self.files:
            raise seq.SequenceError(f"{self.folder}: no frames in left/")

    @property
    def expected_frames(self) -> int | None:
        """How many parts this camera will deliver, when that is known (for progress display)."""
        if self.settings.loop:
            return self.settings.max_frames
        return min(len(self.files), self.settings.max_frames or len(self.files))

    def frames(self) -> Iterator[StereoFrame | FrameError]:
        """Frames at ``rate_fps``, each stamped with the time it is scheduled, as a camera stamps its capture:
        a frame read late (the loop fell behind) keeps its own time, never the time it was read. At rate 0
        a frame is captured when it is asked for."""
        period = 1.0 / self.settings.rate_fps if self.settings.rate_fps > 0 else 0.0
        index, passes = 0, 0
        start_wall, start = time.time(), time.monotonic()
        while True:
            for files in self.files:
                if self.settings.max_frames is not None and index >= self.settings.max_frames:
                    return
                captured = time.time()
                if period:
                    delay = start + index * period - time.monotonic()
                    if delay > 0:
                        time.sleep(delay)
                    captured = start_wall + index * period
                yield self._read(files, index, passes, captured)
                index += 1
            passes += 1
            if not self.settings.loop:
                return

    def _read(self, files: seq.FrameFiles, index: int, passes: int, now: float) -> StereoFrame | FrameError:
        try:
            left = seq.read_image(files.left, f"left image of frame {files.frame_id}")
            right = seq.read_image(files.right, f"right image of frame {files.frame_id}")
        except seq.SequenceError as exc:
            return FrameError(files.frame_id, index, str(exc), now, source=str(self.folder))
        if left.shape != right.shape or left.shape[:2] != (self.calib.height, self.calib.width):
            return FrameError(
                files.frame_id, index,
                f"frame {files.frame_id}: left {left.shape[1]}x{left.shape[0]}, right {right.shape[1]}x{right.shape[0]}, "
                f"calibration {self.calib.width}x{self.calib.height}",
                now, source=str(self.folder),
            )
        meta = {"pass": passes}
        if files.gt is not None:
            meta["gt_disparity"] = str(files.gt)
        if files.labels is not None:
            meta["labels"] = str(files.labels)
        return StereoFrame(files.frame_id, index, left, right, self.calib, now, source=str(self.folder), meta=meta)

    def close(self) -> None:
        return None


def _factory(settings: dict, ctx: PluginContext) -> ReplayCamera:
    return ReplayCamera(ReplaySettings.model_validate(settings, context={"recipe_dir": ctx.recipe_dir}))


def _calibration(settings: dict, ctx: PluginContext) -> Calibration:
    folder = Path(ReplaySettings.model_validate(settings, context={"recipe_dir": ctx.recipe_dir}).path)
    return calibration_from_dict(seq.read_calibration(folder))


@hookimpl
def stereo_inspect_cameras() -> list[PluginSpec]:
    return [
        PluginSpec(
            name="replay",
            kind="camera",
            factory=_factory,
            settings_model=ReplaySettings,
            description="plays a recorded or synthetic sequence folder (left/, right/, calib.yaml)",
            calibration=_calibration,
            frame_rate=lambda settings, ctx: settings.get("rate_fps") or None,
        )
    ]
