"""The 2015 ZED as a UVC camera: one OpenCV capture streaming both eyes side by side.

``ZedUvc`` opens the device (an index such as ``0``, a path such as ``/dev/video0``, or a
recorded side-by-side video file), asks for the resolution/frame rate/exposure/gain (where UVC
allows), and splits each frame into the left and right eye. ``stream()`` runs the capture loop:
when the camera disconnects it reopens it with exponential back-off and reports one ``Missed``
per frame period meanwhile, so that parts passing during the outage are never silently skipped.

``ZedSdk`` does the same through the vendor SDK (``pyzed.sl``) when it is installed; the SDK
rectifies itself. From a Python prompt::

    >>> from drivers.zed_uvc import ZedUvc
    >>> cam = ZedUvc(0, "WVGA", fps=15); cam.open()
    >>> left, right = cam.grab()

This module imports nothing from the rest of stereo-inspect.
"""
from __future__ import annotations

import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers.zed_calibration import RESOLUTIONS

FPS_BY_RESOLUTION = {"WVGA": (15, 30, 60, 100), "HD720": (15, 30, 60), "HD1080": (15, 30), "2K": (15,)}


class ZedError(Exception):
    """The camera cannot be opened or read; the message names the device."""


@dataclass
class Grab:
    index: int
    left: np.ndarray
    right: np.ndarray
    timestamp: float


@dataclass
class Missed:
    index: int
    message: str
    timestamp: float


def parse_device(device: int | str) -> int | str:
    """``0``/``"0"`` -> 0 (a camera index); anything else stays a path."""
    if isinstance(device, int):
        return device
    text = str(device).strip()
    return int(text) if text.isdigit() else text


def is_file_source(device: int | str) -> bool:
    """A recorded video rather than a camera: a path to a regular file outside /dev."""
    if isinstance(device, int):
        return False
    path = Path(device)
    return not str(path).startswith("/dev/") and "://" not in str(device)


def is_recording(device: int | str, backend: str = "uvc") -> bool:
    """A recorded file rather than a live camera: a video file for UVC, an SVO file for the SDK (to which
    any other string is a serial number such as SN11338)."""
    device = parse_device(device)
    if backend == "sdk":
        return isinstance(device, str) and device.endswith((".svo", ".svo2"))
    return is_file_source(device)


def recording_problem(path: str | Path, resolution: str) -> str | None:
    """Why the side-by-side video at ``path`` cannot be played as a ZED at ``resolution``, in words naming it, or
    None: not a video OpenCV can read, or frames of another size. Both are for good, unlike a camera that is
    away for a while, so they are said before a run rather than as one missed frame after another."""
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            return f"{path}: not a video OpenCV can read"
        ok, frame = capture.read()
        if not ok or frame is None:
            return f"{path}: holds no frame"
    finally:
        capture.release()
    size = (frame.shape[1], frame.shape[0])
    width, height = RESOLUTIONS[resolution]
    if size == (2 * width, height):
        return None
    other = [name for name, (w, h) in RESOLUTIONS.items() if (2 * w, h) == size]
    hint = f" (did you mean resolution: {other[0]}?)" if other else ""
    return (f"{path}: recorded at {size[0]}x{size[1]}, but a ZED at {resolution} gives {2 * width}x{height} (two "
            f"eyes side by side){hint}")


def split_side_by_side(frame: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    if frame.ndim == 2:
        frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
    if frame.shape[0] != height or frame.shape[1] != 2 * width:
        raise ZedError(f"frame is {frame.shape[1]}x{frame.shape[0]}, expected {2 * width}x{height} (two eyes side by side)")
    return frame[:, :width].copy(), frame[:, width:].copy()


def capture_time(pos_msec: float, wall_now: float, monotonic_now: float, asked: float) -> float:
    """The wall-clock capture time of a frame from the V4L2 buffer timestamp OpenCV reports as
    CAP_PROP_POS_MSEC (the kernel's monotonic clock, in ms), or, where that is missing or implausible
    (another backend, a driver that leaves it at 0), the time the frame was asked for: never the time
    ``read`` returned, which would call a frame fresh that waited in a queue."""
    if pos_msec > 0:
        age = monotonic_now - pos_msec / 1000.0
        if 0.0 <= age < 10.0:
            return wall_now - age
    return asked


class ZedUvc:
    def __init__(
        self,
        device: int | str = 0,
        resolution: str = "WVGA",
        fps: float = 15.0,
        exposure: float | None = None,
        gain: float | None = None,
        api_preference: int = cv2.CAP_ANY,
    ):
        if resolution not in RESOLUTIONS:
            raise ZedError(f"unknown resolution {resolution!r}; one of {', '.join(RESOLUTIONS)}")
        self.device = parse_device(device)
        self.resolution = resolution
        self.width, self.height = RESOLUTIONS[resolution]
        self.fps, self.exposure, self.gain = fps, exposure, gain
        self.api_preference = api_preference
        self.capture: cv2.VideoCapture | None = None
        self.is_file = is_file_source(self.device)
        self.ended = False  # a recorded file reached its end
        self.last_capture = 0.0  # capture time of the last grabbed pair (wall clock)

    @property
    def name(self) -> str:
        return f"ZED camera {self.device}" if isinstance(self.device, int) else f"ZED {self.device}"

    def open(self) -> None:
        self.close()
        if self.is_file and not Path(self.device).exists():
            raise ZedError(f"{self.name}: no such file or device")
        capture = cv2.VideoCapture(self.device, self.api_preference)
        if not capture.isOpened():
            capture.release()
            raise ZedError(f"{self.name}: cannot open the camera (unplugged, busy, or no permission)")
        if not self.is_file:
            # one frame in the driver's queue: a frame waiting there while the loop was busy would be
            # handed over late yet look fresh
            capture.set(cv2.CAP_PROP_BUFFERSIZE, 1)
            capture.set(cv2.CAP_PROP_FRAME_WIDTH, 2 * self.width)
            capture.set(cv2.CAP_PROP_FRAME_HEIGHT, self.height)
            capture.set(cv2.CAP_PROP_FPS, float(self.fps))
            if self.exposure is not None:
                capture.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)  # V4L2: 1 = manual
                capture.set(cv2.CAP_PROP_EXPOSURE, float(self.exposure))
            if self.gain is not None:
                capture.set(cv2.CAP_PROP_GAIN, float(self.gain))
            got = (int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)), int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)))
            if got != (2 * self.width, self.height):
                capture.release()
                raise ZedError(f"{self.name}: camera gives {got[0]}x{got[1]}, not {2 * self.width}x{self.height} "
                               f"({self.resolution}); is it a ZED?")
        self.capture = capture
        self.ended = False

    def grab(self) -> tuple[np.ndarray, np.ndarray]:
        """One raw (unrectified) pair; raises ``ZedError`` on a failed read. ``last_capture`` is its capture time."""
        if self.capture is None:
            raise ZedError(f"{self.name}: not open")
        asked = time.time()
        ok, frame = self.capture.read()
        if not ok or frame is None:
            if self.is_file:
                self.ended = True
                raise ZedError(f"{self.name}: end of recording")
            raise ZedError(f"{self.name}: no frame (camera disconnected?)")
        self.last_capture = asked if self.is_file else capture_time(
            self.capture.get(cv2.CAP_PROP_POS_MSEC), time.time(), time.monotonic(), asked)
        return split_side_by_side(frame, self.width, self.height)

    def close(self) -> None:
        if self.capture is not None:
            self.capture.release()
        self.capture = None

    def stream(
        self,
        max_frames: int | None = None,
        reconnect_min_s: float = 0.5,
        reconnect_max_s: float = 5.0,
        clock=time.monotonic,
        sleep=time.sleep,
    ) -> Iterator[Grab | Missed]:
        """Pairs in order; while the camera is away, one ``Missed`` per frame period (1/fps).

        A recorded file ends the stream at its end; a camera (or a file not there yet) is reopened with back-off from ``reconnect_min_s`` doubling to ``reconnect_max_s``.
        """
        period = 1.0 / self.fps if self.fps > 0 else 0.1
        index = 0
        backoff = reconnect_min_s
        next_open = clock()
        next_missed = None
        last_error = ""
        while max_frames is None or index < max_frames:
            if self.capture is None:
                now = clock()
                if now >= next_open:
                    try:
                        self.open()
                        backoff = reconnect_min_s
                        next_missed = None
                        continue
                    except ZedError as exc:
                        last_error = str(exc)
                        next_open = now + backoff
                        backoff = min(reconnect_max_s, backoff * 2)
                if next_missed is None:
                    next_missed = now
                wait = min(next_open, next_missed) - clock()
                if wait > 0:
                    sleep(wait)
                if clock() >= next_missed and self.capture is None:
                    yield Missed(index, f"{last_error}; reconnecting (next try in {max(0.0, next_open - clock()):.1f} s)",
                                 time.time())
                    index += 1
                    next_missed += period
                continue
            try:
                left, right = self.grab()
            except ZedError as exc:
                self.close()
                if self.ended:
                    return
                last_error = str(exc)
                next_open = clock() + backoff
                yield Missed(index, last_error, time.time())
                index += 1
                next_missed = clock() + period
                continue
            yield Grab(index, left, right, self.last_capture)
            index += 1


class ZedSdk:
    """The same camera through the vendor SDK (``pyzed.sl``); gives rectified pairs directly."""

    SDK_RESOLUTION = {"WVGA": "VGA", "HD720": "HD720", "HD1080": "HD1080", "2K": "HD2K"}

    def __init__(self, device: int | str = 0, resolution: str = "WVGA", fps: float = 15.0,
                 exposure: float | None = None, gain: float | None = None):
        try:
            import pyzed.sl as sl
        except ImportError:
            raise ZedError("backend sdk needs the ZED SDK's Python module pyzed.sl (not installed); use backend uvc") from None
        self.sl = sl
        self.device, self.resolution, self.fps = parse_device(device), resolution, fps
        self.exposure, self.gain = exposure, gain
        self.width, self.height = RESOLUTIONS[resolution]
        self.camera = None
        self.ended = False
        self.is_file = is_recording(self.device, "sdk")
        self.last_capture = 0.0  # capture time of the last grabbed pair (wall clock)

    @property
    def name(self) -> str:
        return f"ZED {self.device} (SDK)"

    def open(self) -> None:
        sl = self.sl
        init = sl.InitParameters()
        init.camera_resolution = getattr(sl.RESOLUTION, self.SDK_RESOLUTION[self.resolution])
        init.camera_fps = int(self.fps)
        init.depth_mode = sl.DEPTH_MODE.NONE
        init.coordinate_units = sl.UNIT.MILLIMETER
        if isinstance(self.device, int):
            init.set_from_camera_id(self.device)
        elif self.is_file:
            init.set_from_svo_file(self.device)
        else:
            init.set_from_serial_number(int(self.device.removeprefix("SN")))
        camera = sl.Camera()
        status = camera.open(init)
        if status != sl.ERROR_CODE.SUCCESS:
            raise ZedError(f"{self.name}: cannot open ({status})")
        if self.exposure is not None:
            camera.set_camera_settings(sl.VIDEO_SETTINGS.EXPOSURE, int(self.exposure))
        if self.gain is not None:
            camera.set_camera_settings(sl.VIDEO_SETTINGS.GAIN, int(self.gain))
        self.camera = camera
        self._left, self._right, self._runtime = sl.Mat(), sl.Mat(), sl.RuntimeParameters()

    def calibration(self) -> dict:
        """Rectified geometry as reported by the SDK (focal_px, baseline_mm, cx, cy, width, height)."""
        info = self.camera.get_camera_information()
        config = getattr(info, "camera_configuration", info)
        params = config.calibration_parameters
        left = params.left_cam
        return {"focal_px": float(left.fx), "baseline_mm": float(params.get_camera_baseline()), "cx": float(left.cx),
                "cy": float(left.cy), "width": self.width, "height": self.height, "doffs": 0.0}

    def grab(self) -> tuple[np.ndarray, np.ndarray]:
        sl = self.sl
        if self.camera is None:
            raise ZedError(f"{self.name}: not open")
        asked = time.time()
        status = self.camera.grab(self._runtime)
        if status != sl.ERROR_CODE.SUCCESS:
            if status == getattr(sl.ERROR_CODE, "END_OF_SVOFILE_REACHED", None):
                self.ended = True
            raise ZedError(f"{self.name}: grab failed ({status})")
        # a recording's stamps are when it was recorded: its frames are captured when asked for
        self.last_capture = asked if self.is_file else self._capture_time(asked)
        self.camera.retrieve_image(self._left, sl.VIEW.LEFT)
        self.camera.retrieve_image(self._right, sl.VIEW.RIGHT)
        return (np.ascontiguousarray(self._left.get_data()[:, :, :3]),
                np.ascontiguousarray(self._right.get_data()[:, :, :3]))

    def _capture_time(self, asked: float) -> float:
        """The image's capture time as the SDK stamps it (Unix time in ns), or when it was asked for where that
        stamp is implausible (as ``capture_time``)."""
        stamp = self.camera.get_timestamp(self.sl.TIME_REFERENCE.IMAGE).get_nanoseconds() / 1e9
        return stamp if 0.0 <= time.time() - stamp < 10.0 else asked

    def close(self) -> None:
        if self.camera is not None:
            self.camera.close()
            self.camera = None

    @property
    def capture(self):
        return self.camera

    stream = ZedUvc.stream
