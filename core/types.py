"""The data that flows through the engine, one way:

camera -> StereoFrame -> Detection -> disparity -> DefectMeasurement -> Verdict -> outputs -> store.

Plain dataclasses with numpy arrays; no plugin or driver types appear here.
"""
from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Calibration:
    """Rectified stereo geometry.

    Distance from disparity: ``Z = focal_px * baseline_mm / (d + doffs)``.
    ``doffs`` is the difference of the two principal points' x (Middlebury's convention);
    it is 0 for pairs rectified with equal principal points (the ZED, our synthetic scenes).
    """

    focal_px: float
    baseline_mm: float
    cx: float
    cy: float
    width: int
    height: int
    doffs: float = 0.0

    def distance_mm(self, disparity: np.ndarray | float) -> np.ndarray | float:
        return self.focal_px * self.baseline_mm / (np.asarray(disparity, dtype=np.float64) + self.doffs)

    def disparity_px(self, distance_mm: np.ndarray | float) -> np.ndarray | float:
        return self.focal_px * self.baseline_mm / np.asarray(distance_mm, dtype=np.float64) - self.doffs

    def scaled(self, factor: float) -> Calibration:
        """The calibration of the same pair resized by ``factor`` (disparities scale with it)."""
        return Calibration(
            focal_px=self.focal_px * factor,
            baseline_mm=self.baseline_mm,
            cx=self.cx * factor,
            cy=self.cy * factor,
            width=round(self.width * factor),
            height=round(self.height * factor),
            doffs=self.doffs * factor,
        )


@dataclass
class StereoFrame:
    """A rectified pair. Images are HxWx3 uint8 BGR (OpenCV order), same size."""

    frame_id: str
    index: int
    left: np.ndarray
    right: np.ndarray
    calib: Calibration
    timestamp: float
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)


@dataclass
class FrameError:
    """A frame the camera should have delivered but could not (corrupt file, disconnect, ...).

    The engine turns it into an ERROR verdict: a part that could not be inspected is rejected.
    """

    frame_id: str
    index: int
    message: str
    timestamp: float
    source: str = ""

    @property
    def said(self) -> str:
        """The message, naming the frame where it does not already."""
        return self.message if self.frame_id in self.message else f"frame {self.frame_id}: {self.message}"


@dataclass(frozen=True)
class Detection:
    """One detected defect; ``box`` is (x0, y0, x1, y1) in left-image pixels."""

    class_name: str
    confidence: float
    box: tuple[float, float, float, float]

    @property
    def width(self) -> float:
        return self.box[2] - self.box[0]

    @property
    def height(self) -> float:
        return self.box[3] - self.box[1]


@dataclass(frozen=True)
class UncertaintyPart:
    """One term of a deviation's variance: ``variance_mm2``, what makes it, ``cause`` (a clause an integrator
    can act on: the sensor's noise over the texture, a wall the region may hold, a box that may miss its
    defect, ...), and which term it is, ``kind`` (one of ``core.uncertainty_budget.KINDS``)."""

    kind: str
    cause: str
    variance_mm2: float


@dataclass
class DefectMeasurement:
    """What depth says about one detection. ``None`` means "not available" and says why in ``note``.

    deviation_mm: how far the defect's surface lies below (+) or above (-) the surface around it,
    measured along that surface's normal. ``*_sigma_mm``: the standard uncertainty of each (one
    standard deviation, from the fit that measured it). ``method``: ``surface`` (fitted to the images
    themselves, ``core.surface_fit``) or ``disparity`` (from the stereo backend's map alone).
    """

    detection: Detection
    distance_mm: float | None
    deviation_mm: float | None
    valid_fraction: float
    depth_resolution_mm: float | None
    area_mm2: float | None
    note: str = ""
    distance_sigma_mm: float | None = None
    deviation_sigma_mm: float | None = None
    method: str = "disparity"
    # where the images show the surface around a box that could not be measured, when that lies outside the
    # disparities the stereo backend searched (a plate outside the working distance); the engine alarms when
    # that persists
    surface_elsewhere_mm: float | None = None
    # the images show that surface at the searched disparities only with the left and right images swapped
    # (a camera's eyes wired or configured the other way round); the engine alarms when that persists
    eyes_swapped: bool = False
    # the right eye's rows this far (px) from the left's around the box, where the surface fit found them further
    # apart than a rectified camera leaves them (its calibration is not this camera's); the engine alarms when
    # that persists
    rows_apart_px: float | None = None
    # the deviation was read along a groove that crosses the box at this angle (degrees from the image's rows), on
    # the band of the region it runs through rather than on the whole region (``core.band_scan``)
    groove_angle_deg: float | None = None
    # what deviation_sigma_mm is made of (``core.uncertainty_budget``): its variance is their sum; empty where the
    # measurement has no such account (the backend's map alone)
    uncertainty_parts: tuple[UncertaintyPart, ...] = ()

    def quantity(self, name: str) -> float | None:
        if name == "confidence":
            return self.detection.confidence
        return getattr(self, name)

    def uncertainty(self, name: str) -> float | None:
        """The standard uncertainty of ``quantity(name)``; 0 for the detector's confidence (it is exact
        as given), None where the quantity or its uncertainty is unavailable."""
        if name == "confidence":
            return 0.0
        if name == "area_mm2":  # the area goes with Z^2 at a fixed box in pixels
            if self.area_mm2 is None or self.distance_mm is None or self.distance_sigma_mm is None:
                return None
            return 2.0 * self.area_mm2 * self.distance_sigma_mm / self.distance_mm
        return {"distance_mm": self.distance_sigma_mm, "deviation_mm": self.deviation_sigma_mm}.get(name)


class Status(str, enum.Enum):
    """A part's (or a defect's) outcome. FLAG: the measurement could not prove the part in or out of
    its limits and the recipe asks for a manual check; the part is diverted like a reject."""

    PASS = "PASS"
    REJECT = "REJECT"
    ERROR = "ERROR"
    FLAG = "FLAG"

    @property
    def rejects(self) -> bool:
        return self is not Status.PASS


@dataclass
class Verdict:
    status: Status
    reasons: list[str] = field(default_factory=list)


@dataclass
class PartResult:
    """Everything decided about one part; the unit that outputs act on and the store records."""

    part_id: str
    frame_id: str
    index: int
    timestamp: float
    verdict: Verdict
    measurements: list[DefectMeasurement] = field(default_factory=list)
    error: str | None = None
    image_path: str | None = None


@dataclass
class OutputEvent:
    """A command an output sent (or failed to send) for a part; recorded with the part's row.

    ``outcome`` is ``delivered``, ``failed``, or ``alarm`` (could not be delivered in time).
    """

    output: str
    part_id: str | None
    command: str
    outcome: str
    timestamp: float
    detail: str = ""


@dataclass
class Alarm:
    """Something the operator must hear about. ``cause`` names its kind where the source knows it: link
    (the PLC or line cannot be reached), refused (it answered and refused a command), late (a part was
    decided after its command was due), release (a pulse's end not sent), pulse, busy, closed, camera,
    engine, crash, stall (a part stayed in inspection longer than the recipe's ``watchdog_s``), frozen (the
    camera handed over its last images again), image (frames in a row whose images could not show a
    defect), store (the results store could not be written), images (the parts' annotated images could not
    be saved), range (plates in a row outside the stereo search range), swapped (parts in a row whose
    images match only with the left and right exchanged), unmatched (parts in a row whose images match
    nowhere), rectification (parts in a row whose images show the eyes' rows further apart than rectification
    leaves them), behind (a free-running camera's frames went unread while the loop was busy), verify (a
    master part known to be defective passed, or the master parts could not be inspected: no plate is read)."""

    source: str
    message: str
    timestamp: float
    part_id: str | None = None
    cause: str | None = None
