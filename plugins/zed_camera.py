"""Camera ``zed``: the Stereolabs ZED (2015) on the line.

Backend ``uvc`` (default) captures the side-by-side stream through OpenCV and rectifies it with
the camera's factory calibration ``SN<serial>.conf``; backend ``sdk`` uses the vendor SDK
(``pyzed.sl``) when installed. A disconnected camera is reopened with back-off and every frame
period missed meanwhile becomes a ``FrameError`` (the engine rejects that part).

Recipe example::

    camera:
      plugin: zed
      settings:
        device: 0                  # index, /dev/video0, or a recorded side-by-side video
        resolution: WVGA           # WVGA, HD720, HD1080, 2K
        fps: 15
        calibration: SN11338.conf  # relative to the recipe file
        exposure: null             # UVC units; null = automatic
        gain: null
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Literal

from pydantic import Field, ValidationInfo, field_validator, model_validator

from core.contracts import PluginContext, PluginSpec
from core.hookspecs import hookimpl
from core.settings_model import MAX_RECONNECT_MS, Settings
from core.types import Calibration, FrameError, StereoFrame
from drivers.zed_calibration import CalibrationError, StereoRectifier, read_conf, serial_number
from drivers.zed_uvc import (FPS_BY_RESOLUTION, Grab, ZedError, ZedSdk, ZedUvc, is_file_source, is_recording,
                             parse_device, recording_problem)


class ZedSettings(Settings):
    device: int | str = Field(0, description="camera index, /dev/videoN, or a side-by-side video file")
    resolution: Literal["WVGA", "HD720", "HD1080", "2K"] = "WVGA"
    fps: float = Field(15.0, gt=0, le=100)
    calibration: str | None = Field(None, description="the ZED's SN<serial>.conf; relative to the recipe")
    exposure: float | None = Field(None, description="manual exposure (UVC units); null = automatic")
    gain: float | None = Field(None, description="manual gain; null = automatic")
    backend: Literal["uvc", "sdk"] = "uvc"
    rectify_alpha: float = Field(-1.0, ge=-1.0, le=1.0, description="-1 keeps the focal length (as the SDK), 0 crops to valid pixels")
    # each reopen waits that long, every plate meanwhile an ERROR part
    reconnect_min_ms: float = Field(500.0, gt=0, le=MAX_RECONNECT_MS)
    reconnect_max_ms: float = Field(5000.0, gt=0, le=MAX_RECONNECT_MS)
    max_frames: int | None = Field(None, ge=1)

    @field_validator("resolution", mode="before")
    @classmethod
    def _any_case(cls, value):
        # the SDK's names; `inspect bench --resolution` and the docs' prose write them in lower case
        return value.upper() if isinstance(value, str) else value

    @field_validator("calibration")
    @classmethod
    def _calibration_exists(cls, value: str | None, info: ValidationInfo) -> str | None:
        if value is None:
            return None
        base = Path((info.context or {}).get("recipe_dir", "."))
        path = Path(value).expanduser()
        path = path if path.is_absolute() else (base / path).resolve()
        if not path.is_file():
            raise ValueError(f"calibration file not found: {path}")
        return str(path)

    @field_validator("device")
    @classmethod
    def _device_path(cls, value: int | str, info: ValidationInfo) -> int | str:
        device = parse_device(value)
        path = Path(device).expanduser() if isinstance(device, str) else None
        # a recorded video given relative to the recipe (an SDK serial such as SN11338 stays as it is)
        if path is not None and is_file_source(device) and path.suffix and not path.is_absolute():
            base = Path((info.context or {}).get("recipe_dir", "."))
            return str((base / path).resolve())
        return device

    @model_validator(mode="after")
    def _needs_calibration(self):
        if self.backend == "uvc" and self.calibration is None:
            raise ValueError("backend uvc needs calibration: the camera's SN<serial>.conf "
                             "(download from https://calib.stereolabs.com/?SN=<serial>)")
        if self.reconnect_max_ms < self.reconnect_min_ms:
            raise ValueError("reconnect_max_ms must be at least reconnect_min_ms")
        if self.calibration is not None:  # a broken file is the recipe's error, for validate as for run
            try:
                read_conf(self.calibration, self.resolution)
            except CalibrationError as exc:
                raise ValueError(str(exc)) from None
        if self.backend == "uvc" and is_recording(self.device) and Path(self.device).is_file():
            problem = recording_problem(self.device, self.resolution)
            if problem is not None:
                raise ValueError(problem)
        rates = FPS_BY_RESOLUTION[self.resolution]
        if self.fps not in rates and not is_recording(self.device, self.backend):
            # the camera would run at a rate of its own, and the frame periods counted from fps would not be its
            raise ValueError(f"fps {self.fps:g}: a ZED at {self.resolution} runs at {', '.join(map(str, rates))} frames "
                             f"a second")
        return self


class ZedCamera:
    def __init__(self, settings: ZedSettings):
        self.settings = settings
        s = settings
        if s.backend == "sdk":
            self.driver = ZedSdk(s.device, s.resolution, s.fps, s.exposure, s.gain)
            self.rectifier = None
            self.calib: Calibration | None = None  # known once the SDK opened the camera
        else:
            self.driver = ZedUvc(s.device, s.resolution, s.fps, s.exposure, s.gain)
            try:
                self.rectifier = StereoRectifier(read_conf(s.calibration, s.resolution), alpha=s.rectify_alpha)
            except CalibrationError as exc:
                raise ValueError(str(exc)) from None
            self.calib = Calibration(**self.rectifier.as_dict())
        self.source = self.driver.name
        self.serial = serial_number(s.calibration) if s.calibration else ""

    def frames(self) -> Iterator[StereoFrame | FrameError]:
        s = self.settings
        for item in self.driver.stream(s.max_frames, s.reconnect_min_ms / 1000.0, s.reconnect_max_ms / 1000.0):
            frame_id = f"{item.index:06d}"
            if not isinstance(item, Grab):
                yield FrameError(frame_id, item.index, item.message, item.timestamp, source=self.source)
                continue
            try:
                if self.rectifier is not None:
                    left, right = self.rectifier.rectify(item.left, item.right)
                else:
                    left, right = item.left, item.right
                    if self.calib is None:
                        self.calib = Calibration(**self.driver.calibration())
            except (CalibrationError, ZedError) as exc:
                yield FrameError(frame_id, item.index, f"{self.source}: {exc}", item.timestamp, source=self.source)
                continue
            yield StereoFrame(frame_id, item.index, left, right, self.calib, item.timestamp, source=self.source,
                              meta={"serial": self.serial} if self.serial else {})

    def close(self) -> None:
        self.driver.close()


def _factory(settings: dict, ctx: PluginContext) -> ZedCamera:
    validated = ZedSettings.model_validate(settings, context={"recipe_dir": ctx.recipe_dir})
    try:
        return ZedCamera(validated)
    except ZedError as exc:
        raise ValueError(str(exc)) from None


def _calibration(settings: dict, ctx: PluginContext) -> Calibration:
    s = ZedSettings.model_validate(settings, context={"recipe_dir": ctx.recipe_dir})
    if s.calibration is None:  # the SDK reads it from the camera once it is open
        raise ValueError("the ZED's geometry is known only once the SDK has opened it (give calibration)")
    try:
        return Calibration(**StereoRectifier(read_conf(s.calibration, s.resolution), alpha=s.rectify_alpha).as_dict())
    except CalibrationError as exc:
        raise ValueError(str(exc)) from None


def _frame_rate(settings: dict, ctx: PluginContext) -> float | None:
    """The camera's frames a second; None for a recording, which is read as fast as the loop asks (its frames
    are stamped when read, so a slow loop must not read as frames gone by)."""
    s = ZedSettings.model_validate(settings, context={"recipe_dir": ctx.recipe_dir})
    return None if is_recording(s.device, s.backend) else s.fps


@hookimpl
def stereo_inspect_cameras() -> list[PluginSpec]:
    return [
        PluginSpec(
            name="zed",
            kind="camera",
            factory=_factory,
            settings_model=ZedSettings,
            description="Stereolabs ZED over UVC (OpenCV) rectified with its SN<serial>.conf, or through pyzed.sl",
            calibration=_calibration,
            frame_rate=_frame_rate,
        )
    ]


