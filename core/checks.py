"""What the engine checks of what plugins hand it: a camera's frame (and that it is a new one), a
detector's boxes, a backend's map, an output's reports.

A third-party plugin that breaks its contract (``core.contracts``) must cost the part it was working on,
as an ERROR saying what was wrong, and never a measurement read from the wrong pixels. Each function
returns the problem in words, or None.
"""
from __future__ import annotations

import math
from collections.abc import Collection
from typing import Any

import numpy as np

from core.types import Alarm, Detection, FrameError, OutputEvent, StereoFrame
from drivers.stereo_geometry import calibration_problem


def _size(image: np.ndarray) -> str:
    return f"{image.shape[1]}x{image.shape[0]}" if image.ndim >= 2 else f"shape {image.shape}"


def _one_line(value: Any, width: int = 60) -> str:
    """``repr(value)`` on one line (an array's spans several; a problem is said in one), cut to ``width``."""
    return f"{' '.join(repr(value).split()):.{width}}"


def delivery_problem(item: Any) -> str | None:
    """What a camera's ``frames()`` yields, as far as its part can be named from it: a ``StereoFrame`` or a
    ``FrameError`` with a frame id (text) and an index (a whole number, 0 or more)."""
    if not isinstance(item, (StereoFrame, FrameError)):
        return f"the camera delivered a {type(item).__name__} ({_one_line(item)}), not a StereoFrame or a FrameError"
    if not isinstance(item.frame_id, str):
        return f"the camera delivered a frame whose frame_id is {item.frame_id!r}, not text"
    index = item.index
    if not (isinstance(index, (int, np.integer)) and not isinstance(index, bool) and index >= 0):
        return f"the camera delivered frame {item.frame_id} with index {index!r}, not a whole number of 0 or more"
    return None


def frame_problem(frame: StereoFrame) -> str | None:
    """A rectified pair as the contract has it: two HxWx3 uint8 images of one size, the calibration's."""
    for name in ("left", "right"):
        image = getattr(frame, name)
        if not isinstance(image, np.ndarray):
            return f"the camera's {name} image is a {type(image).__name__}, not an array"
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            return f"the camera's {name} image is {image.dtype} of shape {image.shape}, not HxWx3 uint8 BGR"
    if frame.left.shape != frame.right.shape:
        return f"the camera's left and right images differ in size ({_size(frame.left)}, {_size(frame.right)})"
    calib = frame.calib
    for key in ("focal_px", "baseline_mm"):
        value = getattr(calib, key)
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            return f"the camera's calibration has {key} {value!r}: not a positive number, so no distance can be measured"
    problem = calibration_problem(calib.focal_px, calib.baseline_mm, calib.cx, calib.cy, calib.width, calib.height,
                                  calib.doffs)
    if problem is not None:
        return f"the camera's calibration is no camera's: {problem}"
    if frame.left.shape[:2] != (calib.height, calib.width):
        return f"the camera's images are {_size(frame.left)} but its calibration is for {calib.width}x{calib.height}"
    return None


class RepeatedImages:
    """Whether a camera hands over its previous frame's images again, byte for byte.

    Two exposures of a real sensor differ somewhere by its noise; the same bytes twice are a driver
    re-delivering its last buffer (a stalled USB stream, a grab that timed out), and the part in front
    of the camera then was never seen. ``run`` counts such frames in a row."""

    def __init__(self) -> None:
        self._last: tuple[str, np.ndarray, np.ndarray] | None = None
        self.run = 0

    def problem(self, frame: StereoFrame) -> str | None:
        last = self._last
        if (last is not None and last[1].shape == frame.left.shape and np.array_equal(last[1], frame.left)
                and np.array_equal(last[2], frame.right)):
            self.run += 1
            return (f"the camera delivered frame {last[0]}'s images again, byte for byte (a driver re-delivering "
                    f"its last buffer): the part in front of it was not seen")
        self.run = 0
        # copies: a driver may refill the same arrays for its next frame
        self._last = (frame.frame_id, frame.left.copy(), frame.right.copy())
        return None


def detections_problem(detections: Any, classes: Collection[str] | None = None,
                       shape: tuple[int, int] | None = None) -> str | None:
    """A list of ``Detection``s whose boxes are four finite numbers with x0 < x1 and y0 < y1 that overlap
    the HxW image of ``shape`` (where given), whose confidences lie in [0, 1] and whose classes are among
    the detector's ``classes`` (where it states any)."""
    if not isinstance(detections, list):
        return f"the detector returned a {type(detections).__name__}, not a list of detections"
    for d in detections:
        if not isinstance(d, Detection):
            return f"the detector returned a {type(d).__name__} among its detections"
        box = d.box
        if not (len(box) == 4 and all(isinstance(v, (int, float, np.floating, np.integer)) and math.isfinite(v)
                                      for v in box) and box[0] < box[2] and box[1] < box[3]):
            return f"the detector returned a {d.class_name} box {tuple(box)}, not (x0, y0, x1, y1) with x0 < x1, y0 < y1"
        if shape is not None and not (box[0] < shape[1] and box[2] > 0 and box[1] < shape[0] and box[3] > 0):
            # a defect where there is no image: the detector is wrong about this frame, and nothing there can
            # be measured
            return (f"the detector returned a {d.class_name} box {tuple(float(v) for v in box)} outside the "
                    f"{shape[1]}x{shape[0]} image")
        if not (isinstance(d.confidence, (int, float, np.floating, np.integer)) and 0.0 <= d.confidence <= 1.0):
            # a NaN confidence fails every threshold: the defect would be dropped and the part pass
            return f"the detector returned a {d.class_name} with confidence {d.confidence!r}, not a number in [0, 1]"
        if classes and d.class_name not in classes:
            # a rule for one class would never cover it, and the part would pass
            return (f"the detector returned a {d.class_name!r}, not one of the classes it states "
                    f"({', '.join(classes)})")
    return None


# A backend's disparities may overshoot the range it searched by a sub-pixel refinement's reach; both built-in
# backends stay inside it on every evaluation set. Beyond this share outside, the map is not in the pair's
# pixels of disparity at all (a fixed-point map, a map scaled for another resolution): its distances are
# wrong, and its deviations only as wrong as its scale. Zero and below mean "no match" (``depth.valid_mask``).
SEARCH_OVERSHOOT_PX = 1.0
MAX_OUTSIDE_SEARCH = 0.01


def disparity_problem(disparity: Any, shape: tuple[int, int], searched: tuple[float, float] | None = None
                      ) -> str | None:
    """An HxW map of real numbers for the HxW image it was computed from, and, where ``searched`` (lo, hi)
    is given, with its matches (finite values above zero) inside the range the backend was asked to search."""
    if not isinstance(disparity, np.ndarray):
        return f"the stereo backend returned a {type(disparity).__name__}, not an array"
    if disparity.shape != tuple(shape):
        return (f"the stereo backend returned a map of shape {disparity.shape} for a {shape[1]}x{shape[0]} image "
                f"(expected {tuple(shape)})")
    if not (np.issubdtype(disparity.dtype, np.floating) or np.issubdtype(disparity.dtype, np.integer)):
        return f"the stereo backend returned a map of {disparity.dtype}, not numbers"
    if searched is not None:
        lo, hi = searched
        values = disparity[np.isfinite(disparity) & (disparity > 0)]
        outside = float(np.mean((values < lo - SEARCH_OVERSHOOT_PX) | (values > hi + SEARCH_OVERSHOOT_PX))) \
            if values.size else 0.0
        if outside > MAX_OUTSIDE_SEARCH:
            return (f"the stereo backend returned disparities of {float(values.min()):.4g} to {float(values.max()):.4g} "
                    f"px, {outside:.0%} of them outside the {lo:.4g} to {hi:.4g} px it was asked to search: not this "
                    f"pair's disparities in pixels (a fixed-point map, or one scaled for another resolution?)")
    return None


def _text(value: Any, optional: bool = False) -> bool:
    return isinstance(value, str) or (optional and value is None)


def event_problem(event: Any) -> str | None:
    """An ``OutputEvent`` or ``Alarm`` (an output's ``poll`` or ``close`` hands back a list of them) whose
    fields the results store can hold: text where text is meant, a finite time. One it cannot would fail the
    store's write, and the engine would take the store for broken and stop the line."""
    if isinstance(event, Alarm):
        fields = {"source": _text(event.source), "message": _text(event.message),
                  "part_id": _text(event.part_id, True), "cause": _text(event.cause, True)}
    elif isinstance(event, OutputEvent):
        fields = {"output": _text(event.output), "part_id": _text(event.part_id, True),
                  "command": _text(event.command), "outcome": _text(event.outcome), "detail": _text(event.detail)}
    else:
        return f"a {type(event).__name__} ({_one_line(event)}), not an OutputEvent or an Alarm"
    stamp = event.timestamp
    fields["timestamp"] = isinstance(stamp, (int, float)) and not isinstance(stamp, bool) and math.isfinite(stamp)
    wrong = [name for name, ok in fields.items() if not ok]
    if wrong:
        return (f"a {type(event).__name__} whose {', '.join(wrong)} the store cannot hold (text, and a finite time "
                f"in seconds): {event!r:.120}")
    return None
