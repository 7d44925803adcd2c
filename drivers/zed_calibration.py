"""The ZED's factory calibration (``SN<serial>.conf``) and the rectification it implies.

The file is INI: one section per eye and resolution (``[LEFT_CAM_VGA]``, ``[RIGHT_CAM_HD]``, ...)
with ``fx fy cx cy k1 k2 p1 p2 k3``, and ``[STEREO]`` with ``Baseline`` (mm) and per resolution
``TY_<res> TZ_<res>`` (mm) and ``RX_<res> CV_<res> RZ_<res>`` (radians; CV is the rotation about
the vertical axis, "convergence"). The right eye sits at ``(Baseline, TY, TZ)`` from the left
one; ``(RX, CV, RZ)`` is the Rodrigues vector of the rotation between the eyes.

``StereoRectifier`` builds the OpenCV rectification maps once (``stereoRectify`` with
``CALIB_ZERO_DISPARITY``, then ``initUndistortRectifyMap``) and remaps each pair.
After that, a point at distance Z lies on the same row in both eyes at disparity ``f*B/Z``.

From a Python prompt::

    >>> from drivers.zed_calibration import read_conf, StereoRectifier
    >>> rect = StereoRectifier(read_conf("SN11338.conf", "WVGA"))
    >>> rect.focal_px, rect.baseline_mm
    >>> left, right = rect.rectify(raw_left, raw_right)

This module imports nothing from the rest of stereo-inspect.
"""
from __future__ import annotations

import configparser
import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers.stereo_geometry import calibration_problem

# resolution name -> (width, height) of one eye
RESOLUTIONS: dict[str, tuple[int, int]] = {
    "WVGA": (672, 376),
    "HD720": (1280, 720),
    "HD1080": (1920, 1080),
    "2K": (2208, 1242),
}
# resolution name -> suffix used in the .conf file
CONF_SUFFIX = {"WVGA": "VGA", "HD720": "HD", "HD1080": "FHD", "2K": "2K"}
INTRINSIC_KEYS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
# A side-by-side pair: the right eye lies along the left one's x axis and looks the same way, within a
# fraction of a degree on a ZED. Beyond these a file is corrupt or another camera's, and rectifying by it
# would turn the pair into a vertical or crossed one whose baseline comes out 0 or negative.
MAX_OFF_AXIS = 0.1  # the right eye's offset off that axis (TY, TZ), as a share of the baseline
MAX_ROTATION_DEG = 10.0  # the rotation between the eyes (RX, CV, RZ)


class CalibrationError(Exception):
    """The .conf file is missing, unreadable or lacks a value; the message names file and key."""


@dataclass(frozen=True)
class EyeIntrinsics:
    fx: float
    fy: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    @property
    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], dtype=np.float64)

    @property
    def distortion(self) -> np.ndarray:
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], dtype=np.float64)


@dataclass(frozen=True)
class ZedCalibration:
    """Raw (unrectified) calibration of one resolution."""

    resolution: str
    width: int
    height: int
    left: EyeIntrinsics
    right: EyeIntrinsics
    baseline_mm: float
    ty_mm: float = 0.0
    tz_mm: float = 0.0
    rx: float = 0.0
    cv: float = 0.0
    rz: float = 0.0
    source: str = ""

    @property
    def rotation(self) -> np.ndarray:
        """R taking left-eye coordinates to right-eye coordinates."""
        rot, _ = cv2.Rodrigues(np.array([self.rx, self.cv, self.rz], dtype=np.float64))
        return rot

    @property
    def translation(self) -> np.ndarray:
        """T of ``x_right = R x_left + T`` (mm): the right eye is ``Baseline`` to the right."""
        return np.array([[-self.baseline_mm], [self.ty_mm], [self.tz_mm]], dtype=np.float64)


def _serial_of(path: Path) -> str:
    match = re.search(r"SN(\d+)", path.name)
    return match.group(1) if match else ""


def read_conf(path: str | Path, resolution: str = "WVGA") -> ZedCalibration:
    path = Path(path)
    if resolution not in RESOLUTIONS:
        raise CalibrationError(f"unknown resolution {resolution!r}; one of {', '.join(RESOLUTIONS)}")
    if not path.is_file():
        raise CalibrationError(f"{path}: calibration file not found (the ZED's SN<serial>.conf)")
    parser = configparser.ConfigParser()
    parser.optionxform = str  # keep the keys' case
    try:
        parser.read_string(path.read_text(encoding="utf-8-sig", errors="replace"))  # Notepad writes a BOM
    except configparser.Error as exc:
        raise CalibrationError(f"{path}: not an INI calibration file ({str(exc).splitlines()[0]})") from None
    suffix = CONF_SUFFIX[resolution]

    def section(name: str) -> configparser.SectionProxy:
        if not parser.has_section(name):
            raise CalibrationError(f"{path}: section [{name}] missing")
        return parser[name]

    def number(sec: configparser.SectionProxy, key: str, default: float | None = None) -> float:
        lookup = {k.lower(): v for k, v in sec.items()}
        raw = lookup.get(key.lower())
        if raw is None:
            if default is not None:
                return default
            raise CalibrationError(f"{path}: [{sec.name}] {key} missing")
        try:
            value = float(raw)
        except ValueError:
            value = float("nan")
        if not np.isfinite(value):
            raise CalibrationError(f"{path}: [{sec.name}] {key} = {raw!r} is not a number")
        return value

    def eye(name: str) -> EyeIntrinsics:
        sec = section(name)
        intrinsics = EyeIntrinsics(*(number(sec, k, None if k in ("fx", "fy", "cx", "cy") else 0.0)
                                     for k in INTRINSIC_KEYS))
        for key in ("fx", "fy"):
            if getattr(intrinsics, key) <= 0:
                raise CalibrationError(f"{path}: [{name}] {key} must be positive (px), got {getattr(intrinsics, key)}")
        return intrinsics

    stereo = section("STEREO")
    width, height = RESOLUTIONS[resolution]
    calib = ZedCalibration(
        resolution=resolution,
        width=width,
        height=height,
        left=eye(f"LEFT_CAM_{suffix}"),
        right=eye(f"RIGHT_CAM_{suffix}"),
        baseline_mm=number(stereo, "Baseline"),
        ty_mm=number(stereo, f"TY_{suffix}", number(stereo, "TY", 0.0)),
        tz_mm=number(stereo, f"TZ_{suffix}", number(stereo, "TZ", 0.0)),
        rx=number(stereo, f"RX_{suffix}", 0.0),
        cv=number(stereo, f"CV_{suffix}", 0.0),
        rz=number(stereo, f"RZ_{suffix}", 0.0),
        source=str(path),
    )
    if calib.baseline_mm <= 0:
        raise CalibrationError(f"{path}: [STEREO] Baseline must be positive (mm), got {calib.baseline_mm}")
    for name, eye_ in ((f"LEFT_CAM_{suffix}", calib.left), (f"RIGHT_CAM_{suffix}", calib.right)):
        problem = calibration_problem(eye_.fx, calib.baseline_mm, eye_.cx, eye_.cy, width, height)
        if problem is not None:
            raise CalibrationError(f"{path}: {problem} (from [{name}] fx, cx, cy and [STEREO] Baseline)")
    off_axis = float(np.hypot(calib.ty_mm, calib.tz_mm))
    if off_axis > MAX_OFF_AXIS * calib.baseline_mm:
        raise CalibrationError(f"{path}: [STEREO] TY_{suffix}, TZ_{suffix} put the right eye {off_axis:.4g} mm off the "
                               f"line through the eyes, {off_axis / calib.baseline_mm:.0%} of the {calib.baseline_mm:g} mm "
                               f"baseline: no side-by-side camera's (at most {MAX_OFF_AXIS:.0%})")
    turned = float(np.degrees(np.linalg.norm([calib.rx, calib.cv, calib.rz])))
    if turned > MAX_ROTATION_DEG:
        raise CalibrationError(f"{path}: [STEREO] RX_{suffix}, CV_{suffix}, RZ_{suffix} turn the right eye by "
                               f"{turned:.3g} degrees against the left: no side-by-side camera's (at most "
                               f"{MAX_ROTATION_DEG:g}; the angles are radians)")
    return calib


class StereoRectifier:
    """Rectification maps for one calibration; ``rectify(left, right)`` gives the rectified pair."""

    def __init__(self, calib: ZedCalibration, alpha: float = -1.0):
        """``alpha`` as in ``cv2.stereoRectify``: -1 (default) keeps the focal length of the raw eyes
        (as the ZED SDK does; corners may show a thin black border), 0 crops to valid pixels only
        (the focal length shrinks with the barrel distortion), 1 keeps every source pixel."""
        self.calib = calib
        size = (calib.width, calib.height)
        r1, r2, p1, p2, q, _, _ = cv2.stereoRectify(
            calib.left.matrix, calib.left.distortion, calib.right.matrix, calib.right.distortion,
            size, calib.rotation, calib.translation, flags=cv2.CALIB_ZERO_DISPARITY, alpha=alpha, newImageSize=size,
        )
        self.R1, self.R2, self.P1, self.P2, self.Q = r1, r2, p1, p2, q
        self.maps_left = cv2.initUndistortRectifyMap(calib.left.matrix, calib.left.distortion, r1, p1, size, cv2.CV_16SC2)
        self.maps_right = cv2.initUndistortRectifyMap(calib.right.matrix, calib.right.distortion, r2, p2, size, cv2.CV_16SC2)
        self.focal_px = float(p1[0, 0])
        self.cx, self.cy = float(p1[0, 2]), float(p1[1, 2])
        self.baseline_mm = float(-p2[0, 3] / p2[0, 0])
        self.doffs = float(p2[0, 2] - p1[0, 2])  # 0 with CALIB_ZERO_DISPARITY
        self.width, self.height = size

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if left.shape[:2] != (self.height, self.width) or right.shape[:2] != (self.height, self.width):
            raise CalibrationError(
                f"image {left.shape[1]}x{left.shape[0]} does not match the calibration's {self.width}x{self.height} "
                f"({self.calib.resolution})"
            )
        return (
            cv2.remap(left, *self.maps_left, cv2.INTER_LINEAR),
            cv2.remap(right, *self.maps_right, cv2.INTER_LINEAR),
        )

    def rectify_points(self, points: np.ndarray, eye: str = "left") -> np.ndarray:
        """Raw pixel coordinates (Nx2) of one eye -> rectified pixel coordinates."""
        intr = self.calib.left if eye == "left" else self.calib.right
        r, p = (self.R1, self.P1) if eye == "left" else (self.R2, self.P2)
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 1, 2)
        return cv2.undistortPoints(pts, intr.matrix, intr.distortion, R=r, P=p).reshape(-1, 2)

    def as_dict(self) -> dict:
        """The rectified geometry with the keys of a sequence folder's ``calib.yaml``."""
        return {
            "focal_px": self.focal_px,
            "baseline_mm": self.baseline_mm,
            "cx": self.cx,
            "cy": self.cy,
            "width": self.width,
            "height": self.height,
            "doffs": self.doffs,
        }


def serial_number(path: str | Path) -> str:
    """The serial in ``SN<serial>.conf``, or ''."""
    return _serial_of(Path(path))
