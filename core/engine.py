"""The run loop: camera -> detections -> disparity -> measurements -> verdict -> store -> outputs.

Nothing a frame does can pass a part it could not inspect: any failure on the way (a frame the
camera could not deliver, a stereo or detector exception, a missing measurement a rule needs)
becomes an ERROR verdict, which the outputs reject like any other reject.
"""
from __future__ import annotations

import copy
import math
import os
import sqlite3
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from core import depth, stereo_memory
from core.checks import (RepeatedImages, delivery_problem, detections_problem, disparity_problem, event_problem,
                         frame_problem)
from core.clock_steps import ClockSteps
from core.contracts import PluginContext, missing_members
from core.decision import decide, error_verdict
from core.devices import plugin_device
from core.depth import DepthRule, measure_frame
from core.frame_source import DetectAhead, OneAtATime
from core.image_quality import image_problem, image_stats
from core.interrupts import raise_if_interrupted
from core.part_images import PartImages
from core.plate_view import PlateElsewhere, plate_elsewhere
from core.recipe import LoadedRecipe
from core.recipe.loader import (camera_answer, detector_settings, file_sha256, named_classes, output_delays_s,
                                unknown_class_message)
from core.recipe.schema import StereoSection
from core.registry import Registry, default_registry
from core.store import ResultsStore, StoreError, damaged, store_problem
from core.stereo_region import disparity_around
from core.types import (Alarm, Calibration, DefectMeasurement, Detection, FrameError, OutputEvent, PartResult, Status,
                        StereoFrame, Verdict)
from core.unread_frames import UnreadFrame, UnreadFrames
from core.watchdog import StallWatch

EXIT_OK, EXIT_USAGE, EXIT_PART_ERRORS, EXIT_ALARMS, EXIT_INTERRUPTED = 0, 2, 3, 4, 130
CAMERA_LOST_AFTER = 3  # consecutive frames the camera could not deliver
CAMERA_WAIT = "camera"  # the watchdog's key for a free-running camera's wait for its next frame
CAMERA_OPEN_S = 30.0  # the longest a free-running camera's first frame may take (the device opening)
_END = object()  # the camera's frames ran out (a None it yields is a breach, not the end)
# how far ahead of this computer's clock a frame's capture time may lie (a clock set back while it was
# inspected); further, or not a number, and the stamp is not this computer's time at capture
STAMP_AHEAD_S = 1.0


class SetupError(Exception):
    """The run cannot start (a plugin failed to initialise); the message names the recipe key."""


@dataclass
class Pipeline:
    camera: Any
    stereo: Any
    detector: Any
    outputs: list[tuple[str, Any]]

    def warm_up(self) -> None:
        """Run the detector's and the stereo backend's optional ``warm_up`` and a depth measurement, before the
        first part: their first calls build the model and compile kernels (on the 2-core development machine 74 s
        for torch_sgm's and 14 s for the depth measurement's with numba's cache empty), which would make the first
        part late for the actuator and trip the watchdog. The backend's first: torch_sgm's has depth's kernels
        compiled beside its own (``plugins/torch_sgm/kernel_warm_up.py``). ``detect`` itself is called once per
        part and for nothing else: a detector that hands out each frame's boxes in turn (an evaluation's true
        boxes) stays in step with the parts. A stage that fails here fails on the parts too, where the failure is
        reported per part."""
        for stage in (self.detector, self.stereo):
            warm_up = getattr(stage, "warm_up", None)
            if callable(warm_up):
                try:
                    warm_up()
                except Exception:
                    pass
        try:
            depth.warm_up()
        except Exception:
            pass

    def close(self) -> None:
        self.camera.close()


def resolve_threads(threads: int | str) -> int:
    """The recipe's ``threads``: a count, or auto = half the cores (at least one)."""
    if threads == "auto":
        return max(1, (os.cpu_count() or 2) // 2)
    return int(threads)


def apply_threads(threads: int | str) -> int:
    """Set torch's and OpenCV's CPU threads for this process (and the BLAS libraries' to one,
    ``single_threaded_blas``); returns the count."""
    import torch

    n = resolve_threads(threads)
    torch.set_num_threads(n)
    cv2.setNumThreads(n)
    single_threaded_blas()
    return n


def command_threads(threads: int | None) -> None:
    """A command's ``--threads``: that many torch and OpenCV threads (``apply_threads``); without it torch
    keeps its own count and only the BLAS libraries go to one thread."""
    if threads:
        apply_threads(threads)
    else:
        single_threaded_blas()


def single_threaded_blas() -> None:
    """NumPy's and OpenCV's BLAS on one thread. The project's matrix products are small (a surface fit's
    normal equations and covariance), and the threads OpenBLAS leaves spinning after each one slowed
    the detector that runs next 2-3x (docs/research-log.md, the inspection loop)."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, user_api="blas")


def make_plugin(loaded: LoadedRecipe, registry: Registry, ctx: PluginContext, kind: str, name: str, key: str,
                settings: dict) -> Any:
    """The ``kind`` plugin ``name`` the recipe key ``key`` chose, built from ``settings`` and checked for its
    kind's methods; ``SetupError`` naming the key where it cannot be."""
    try:
        made = registry.get(kind, name).spec.factory(settings, ctx)
    except Exception as exc:  # a plugin's own failure, reported against the recipe key that chose it
        raise SetupError(f"{loaded.path}: {key}: {name}: {exc}") from exc
    missing = missing_members(made, kind)
    if missing:
        raise SetupError(f"{loaded.path}: {key}: {name}: its factory returned an instance of {type(made).__name__}, which has no "
                         f"{', '.join(missing)} (a {kind} plugin's object needs them)")
    return made


def build_detector(loaded: LoadedRecipe, registry: Registry, ctx: PluginContext) -> Any:
    """The recipe's detector, checked against the classes the recipe names."""
    recipe = loaded.recipe
    detector = make_plugin(loaded, registry, ctx, "detector", recipe.detector.plugin, "detector", detector_settings(loaded))
    # the same check as the recipe's validation, for detectors that state their classes only once built
    for key, name in named_classes(recipe):
        if name not in detector.class_names:
            raise SetupError(loaded.describe(key, unknown_class_message(name, list(detector.class_names))))
    return detector


def plugin_context(loaded: LoadedRecipe, device: str) -> PluginContext:
    """What the recipe's plugins are built with on ``device`` (``auto``: CUDA where torch sees one, and the
    plugins told that nobody named it)."""
    return PluginContext(recipe_dir=loaded.directory, recipe_name=loaded.recipe.name, **plugin_device(device))


def build_pipeline(loaded: LoadedRecipe, registry: Registry, device: str = "auto") -> Pipeline:
    recipe = loaded.recipe
    ctx = plugin_context(loaded, device)

    def make(kind: str, name: str, key: str, settings: dict) -> Any:
        return make_plugin(loaded, registry, ctx, kind, name, key, settings)

    camera = make("camera", recipe.camera.plugin, "camera", loaded.plugin_settings["camera"])
    stereo = make("stereo", recipe.stereo.backend, "stereo", loaded.plugin_settings["stereo"])
    detector = build_detector(loaded, registry, ctx)
    outputs = [
        (o.plugin, make("output", o.plugin, f"outputs.{i}", loaded.plugin_settings[f"outputs.{i}"]))
        for i, o in enumerate(recipe.outputs)
    ]
    return Pipeline(camera, stereo, detector, outputs)


def check_stereo_memory(loaded: LoadedRecipe, backend: Any, registry: Registry) -> None:
    """``SetupError`` where the recipe matches whole frames (``region: full``) that cannot be matched in the
    memory available, from the geometry the camera states (``core.stereo_memory``). Crops are checked one by
    one as they come."""
    if loaded.recipe.stereo.region != "full":
        return
    problem = stereo_memory.recipe_problem(loaded, backend, registry)
    if problem is not None:
        raise SetupError(loaded.describe(("stereo",), problem))


def disparity_range(stereo: StereoSection, calib: Calibration) -> tuple[float, float]:
    """The search range in full-resolution pixels (``StereoSection.search_range``)."""
    return stereo.search_range(calib)


def compute_disparity(backend: Any, frame: StereoFrame, lo: float, hi: float, scale: float) -> np.ndarray:
    """Disparity at full resolution; with ``scale < 1`` the pair is matched smaller and scaled back.
    ``StageFailed`` where the backend's map is not one for the images it was given (``core.checks``)."""
    if scale >= 1.0:
        return match_pair(backend, frame.left, frame.right, lo, hi)
    size = (max(1, round(frame.left.shape[1] * scale)), max(1, round(frame.left.shape[0] * scale)))
    small_l = cv2.resize(frame.left, size, interpolation=cv2.INTER_AREA)
    small_r = cv2.resize(frame.right, size, interpolation=cv2.INTER_AREA)
    small = match_pair(backend, small_l, small_r, lo * scale, hi * scale)
    full = cv2.resize(small, (frame.left.shape[1], frame.left.shape[0]), interpolation=cv2.INTER_NEAREST)
    return full / scale


def match_pair(backend: Any, left: np.ndarray, right: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """The backend's HxW float32 map of the pair, searched over ``lo <= d < hi``.

    A left pixel less than ``lo`` columns from the image's left edge has its match left of the right
    image, so the backend is given the pair without them: the left image from column ``s = floor(lo)``,
    the right image without its last ``s`` columns, searched over ``lo - s <= d < hi - s``. The same
    pixels match the same pixels; the backend's work and the pixels it fills by guessing shrink (a
    crop's first columns, which are there only for the right image's sake, are a third of it)."""
    shift = max(0, min(math.floor(lo), left.shape[1] - 1))
    width = left.shape[1] - shift
    # refused here rather than killed by the kernel halfway, with the rejects queued before it
    problem = stereo_memory.memory_problem(backend, left.shape[0], width, stereo_memory.search_disparities(lo, hi))
    if problem is not None:
        raise StageFailed(problem)
    if shift == 0:
        # copies, as the shifted pair below is: the surface fit reads these pixels after the backend
        return _checked(backend.compute(left.copy(), right.copy(), lo, hi), left.shape[:2], (lo, hi))
    pair = np.ascontiguousarray(left[:, shift:]), np.ascontiguousarray(right[:, :width])
    matched = _checked(backend.compute(*pair, lo - shift, hi - shift), pair[0].shape[:2], (lo - shift, hi - shift))
    out = np.full(left.shape[:2], np.nan, dtype=np.float32)
    # zero and below are "no match" (``depth.valid_mask``): shifted, they would read as the range's far end
    out[:, shift:] = np.where(matched > 0, matched + shift, np.nan)
    return out


def _checked(disparity: Any, shape: tuple[int, int], searched: tuple[float, float]) -> np.ndarray:
    problem = disparity_problem(disparity, shape, searched)
    if problem is not None:
        raise StageFailed(problem)
    return disparity if disparity.dtype == np.float32 else disparity.astype(np.float32)


def frame_disparity(backend: Any, frame: StereoFrame, stereo: StereoSection, detections: list[Detection],
                    rule: DepthRule) -> np.ndarray:
    """The frame's disparity as the recipe asks: the whole frame (``region: full``), or only the boxes,
    their depth rings and a margin (``region: defects``, NaN elsewhere). Always from this frame."""
    lo, hi = disparity_range(stereo, frame.calib)
    if stereo.region == "full":
        return compute_disparity(backend, frame, lo, hi, stereo.scale)
    return disparity_around(lambda crop: compute_disparity(backend, crop, lo, hi, stereo.scale), frame,
                            [d.box for d in detections], rule, stereo.margin_px, hi, stereo.scale)


@dataclass
class FrameOutcome:
    part: PartResult
    per_defect: list[tuple[Status, list[str]]]  # each measurement's status and reasons
    image: np.ndarray | None
    timings: dict[str, float] = field(default_factory=dict)
    plate: PlateElsewhere | None = None  # where a frame whose defects placed no plate shows it, if elsewhere

    @property
    def defect_status(self) -> list[Status]:
        return [status for status, _ in self.per_defect]


@dataclass
class Detected:
    """What the detection stage made of one frame: its detections, or the failure to report."""

    detections: list[Detection] | None
    seconds: float = 0.0
    error: str | None = None


def _read_only(image: Any) -> Any:
    """A view of ``image`` that cannot be written: stereo and depth read the same pixels after the detector, so
    a detector that drew on its input would have them measure its drawing."""
    if not isinstance(image, np.ndarray):
        return image
    view = image.view()
    view.flags.writeable = False
    return view


def detect_frame(item: StereoFrame | FrameError, pipeline: Pipeline, recipe) -> Detected | None:
    """Stage 1 of a frame (None for a FrameError, which has nothing to detect on)."""
    if isinstance(item, FrameError):
        return None
    t0 = time.perf_counter()
    try:
        found = pipeline.detector.detect(_read_only(item.left))
    except Exception as exc:  # reported on the part by inspect_frame
        raise_if_interrupted(exc)
        return Detected(None, time.perf_counter() - t0, f"{type(exc).__name__}: {exc}")
    kept, problem = kept_detections(found, pipeline.detector, recipe, item.left.shape[:2])
    return Detected(kept, time.perf_counter() - t0, problem)


def kept_detections(found: Any, detector: Any, recipe, shape: tuple[int, int]) -> tuple[list[Detection] | None, str | None]:
    """What a detector returned on an HxW image of ``shape``, checked against its contract
    (``detections_problem``) and cut to the recipe's confidence and classes: (the detections kept, None),
    or (None, the problem in words)."""
    problem = detections_problem(found, getattr(detector, "class_names", None), shape)
    if problem is not None:
        return None, problem
    return _filter(found, recipe.detector.confidence, recipe.detector.classes), None


def frame_age_limit_s(loaded: LoadedRecipe, registry: Registry | None = None) -> float | None:
    """``camera.max_frame_age_ms``, or the shortest delay from the camera to an output's actuator, or None."""
    if loaded.recipe.camera.max_frame_age_ms is not None:
        return loaded.recipe.camera.max_frame_age_ms / 1000.0
    delays = [d for _, d in output_delays_s(loaded, registry or default_registry()) if d]
    return min(delays) if delays else None


def inspect_frame(item: StereoFrame | FrameError, part_id: str, pipeline: Pipeline, loaded: LoadedRecipe, rule: DepthRule,
                  detected: Detected | None = None, age_limit_s: float | None = None,
                  clock: Callable[[], float] = time.time, refused: str | None = None) -> FrameOutcome:
    """One frame through every stage; ``detected`` when its detection already ran (``stereo.concurrent``).
    A frame older than ``age_limit_s`` when it gets here is an ERROR: its part has passed the actuator;
    so is one the loop ``refused`` (``frame_refusal``: the frame before's images again, or an image that
    cannot show a defect)."""
    recipe = loaded.recipe
    now = clock()
    stamp_problem = capture_time_problem(item.timestamp, now)
    if stamp_problem is not None:
        # its reject is timed from now, the best that is known of when the plate passed the camera
        message = f"frame {item.frame_id}: {stamp_problem}" + (
            f" (and {item.message})" if isinstance(item, FrameError) else "")
        part = PartResult(part_id, item.frame_id, item.index, now, error_verdict(f"camera: {message}"), error=message)
        return FrameOutcome(part, [], None)
    if isinstance(item, FrameError):
        part = PartResult(part_id, item.frame_id, item.index, item.timestamp, error_verdict(f"camera: {item.message}"), error=item.message)
        return FrameOutcome(part, [], None)
    age = now - item.timestamp
    if age_limit_s is not None and age > age_limit_s:
        message = (f"frame {item.frame_id}: reached inspection {1000 * age:.0f} ms after its capture, later than "
                   f"{1000 * age_limit_s:.0f} ms (camera.max_frame_age_ms, or the shortest delay to an actuator)")
        part = PartResult(part_id, item.frame_id, item.index, item.timestamp, error_verdict(message), error=message)
        return FrameOutcome(part, [], None)

    problem = frame_problem(item) or refused
    if problem is not None:
        message = f"frame {item.frame_id}: {problem}"
        part = PartResult(part_id, item.frame_id, item.index, item.timestamp, error_verdict(message), error=message)
        return FrameOutcome(part, [], None)
    detected = detected or detect_frame(item, pipeline, recipe)
    timings: dict[str, float] = {"detection": detected.seconds}
    stage = "detection"
    try:
        if detected.error is not None:
            raise StageFailed(detected.error)
        detections = detected.detections
        stage = "stereo"  # its search range, which the plate check reads too, may not fit the frame
        searched = disparity_range(recipe.stereo, item.calib)
        if not detections:
            # nothing measured says where the plate is: the images must not show it only where no search looks
            stage = "plate check"
            plate = _timed_plate_check(item, searched, timings)
            if plate is not None:
                return _elsewhere_outcome(item, part_id, plate, searched, timings)
        measurements = []
        if detections or recipe.stereo.schedule == "every_frame":
            stage = "stereo"
            t0 = time.perf_counter()
            disparity = frame_disparity(pipeline.stereo, item, recipe.stereo, detections, rule)
            timings["stereo"] = time.perf_counter() - t0
            stage = "depth"
            t0 = time.perf_counter()
            measurements = measure_frame(disparity, detections, item, rule, searched)
            timings["depth"] = time.perf_counter() - t0
        stage = "decision"
        verdict, per_defect = decide(measurements, recipe.decision)
        if measurements and not any(_places_the_plate(m) for m in measurements):
            # no defect measured, none seen elsewhere around its box: the frame's patches may still say where
            stage = "plate check"
            plate = _timed_plate_check(item, searched, timings)
            if plate is not None:
                return _elsewhere_outcome(item, part_id, plate, searched, timings, measurements, verdict, per_defect)
    except Exception as exc:  # one part's failure must not stop the line; it rejects that part
        raise_if_interrupted(exc)
        what = str(exc) if isinstance(exc, StageFailed) else f"{type(exc).__name__}: {exc}"
        message = f"frame {item.frame_id}: {stage} failed: {what}"
        part = PartResult(part_id, item.frame_id, item.index, item.timestamp, error_verdict(message), error=message)
        return FrameOutcome(part, [], item.left, timings)
    part = PartResult(part_id, item.frame_id, item.index, item.timestamp, verdict, measurements)
    return FrameOutcome(part, per_defect, item.left, timings)


def _places_the_plate(m: DefectMeasurement) -> bool:
    """Whether a defect's measurement says where its plate is: measured, or seen outside the searched range,
    with the eyes swapped or with their rows apart around its box."""
    return (m.deviation_mm is not None or m.surface_elsewhere_mm is not None or m.eyes_swapped
            or m.rows_apart_px is not None)


def _elsewhere_outcome(item: StereoFrame, part_id: str, plate: PlateElsewhere, searched: tuple[float, float],
                       timings: dict[str, float], measurements: list[DefectMeasurement] = (),
                       verdict: Verdict | None = None, per_defect: list = ()) -> FrameOutcome:
    """The ERROR part of a frame whose images show the plate ``plate`` says, not where the search looked: one
    without defects, or whose ``measurements`` (judged ``verdict``, ``per_defect``) placed it nowhere."""
    said = "no defect could be measured, and" if measurements else "no defect found, but"
    why = ("a part whose images cannot be checked does not pass" if plate.unmatched or plate.rows_apart else
           "a plate inspected where the recipe does not expect it does not pass")
    message = f"frame {item.frame_id}: {said} {plate.describe(searched)}; {why}"
    reasons = [message, *(verdict.reasons if verdict is not None else [])]
    part = PartResult(part_id, item.frame_id, item.index, item.timestamp, Verdict(Status.ERROR, reasons),
                      list(measurements), error=message)
    return FrameOutcome(part, list(per_defect), item.left, timings, plate)


def _timed_plate_check(item: StereoFrame, searched: tuple[float, float], timings: dict[str, float]):
    """``plate_view.plate_elsewhere`` of the frame, its time added to ``timings``."""
    t0 = time.perf_counter()
    plate = plate_elsewhere(item.left, item.right, item.calib, searched)
    timings["plate check"] = timings.get("plate check", 0.0) + time.perf_counter() - t0
    return plate


def capture_time_problem(timestamp: Any, now: float) -> str | None:
    """Why a camera's ``timestamp`` is not this computer's ``time.time()`` at capture, or None. The outputs
    time each reject from it: a NaN would never fall due, a stamp from another clock fall due hours off."""
    if not (isinstance(timestamp, (int, float)) and math.isfinite(timestamp)):
        return f"the camera stamped it {timestamp!r}, not a time"
    if timestamp - now > STAMP_AHEAD_S:
        return (f"the camera stamped it {timestamp - now:.1f} s ahead of this computer's clock: a frame's stamp must "
                f"be time.time() at its capture")
    return None


class SurfaceElsewhere:
    """Parts in a row whose images show the plate where the stereo backend did not search, around their defects
    or, for a part without defects, anywhere in the frame (``core.plate_view``): at disparities outside its range
    (``DefectMeasurement.surface_elsewhere_mm``: a plate outside the working distance), only with the left and
    right images swapped (``eyes_swapped``: a camera delivering its eyes the other way round), or nowhere, the
    two images not showing one scene (``PlateElsewhere.unmatched``); and parts whose images show the eyes' rows
    further apart than rectification leaves them (``rows_apart_px``: a calibration that is not this camera's).
    A part with a measured deviation ends such a run."""

    def __init__(self, stereo: StereoSection):
        self.stereo = stereo
        self.runs = {"range": 0, "swapped": 0, "unmatched": 0, "rectification": 0}

    def alarms(self, part: PartResult, plate: PlateElsewhere | None = None) -> list[Alarm]:
        """The alarm of each cause whose run reaches CAMERA_LOST_AFTER parts with this one (once per run);
        ``plate``: where the images of a part without defects show the plate, if elsewhere."""
        found = [m.surface_elsewhere_mm for m in part.measurements if m.surface_elsewhere_mm is not None]
        if plate is not None and not plate.swapped and not plate.unmatched and not plate.rows_apart:
            found.append(plate.distance_mm)
        seen = {"range": bool(found),
                "swapped": any(m.eyes_swapped for m in part.measurements) or (plate is not None and plate.swapped),
                "unmatched": plate is not None and bool(plate.unmatched)}
        rows = [m.rows_apart_px for m in part.measurements if m.rows_apart_px is not None]
        if plate is not None and plate.rows_apart:
            rows.append(float(plate.rows_apart))
        seen["rectification"] = bool(rows)
        measured = any(m.deviation_mm is not None for m in part.measurements)
        for cause, now in seen.items():
            if now:
                self.runs[cause] += 1
            elif measured:
                self.runs[cause] = 0
        if self.stereo.working_distance_mm is not None:
            near, far = self.stereo.working_distance_mm
            searched = f"stereo.working_distance_mm ({near:g}-{far:g} mm)"
        else:
            searched = "the disparities stereo.min_disparity and max_disparity search"
        what = {
            "range": (f"plates outside the working distance: {CAMERA_LOST_AFTER} parts in a row whose images show "
                      f"the plate at about {float(np.median(found or [np.nan])):.0f} mm (last: frame "
                      f"{part.frame_id}), outside {searched}", "the plates or the recipe are set right"),
            "swapped": (f"left and right images swapped: {CAMERA_LOST_AFTER} parts in a row whose images show the "
                        f"plate within {searched} only with the camera's left and right images exchanged "
                        f"(last: frame {part.frame_id})", "the camera delivers its left eye's image as the left"),
            "unmatched": (f"images that do not match: {CAMERA_LOST_AFTER} parts in a row whose left and right images "
                          f"match nowhere (last: frame {part.frame_id})",
                          "the camera delivers both eyes' images of one moment, whole"),
            "rectification": (f"camera not rectified: {CAMERA_LOST_AFTER} parts in a row whose images show the right "
                              f"eye's rows {float(np.median(rows or [np.nan])):+.1f} px from the left eye's (last: "
                              f"frame {part.frame_id})", "the camera's own calibration file is in the recipe"),
        }
        return [Alarm("depth", f"{said}; they cannot be inspected and are rejected as ERROR until {until}",
                      time.time(), part.part_id, cause)
                for cause, (said, until) in what.items() if seen[cause] and self.runs[cause] == CAMERA_LOST_AFTER]


def frame_refusal(item: StereoFrame | FrameError, repeats: RepeatedImages, check) -> tuple[str | None, str | None]:
    """Why a frame the camera delivered in good order may not decide its part: (its images are the frame
    before's, in words, or None; its images cannot show a defect, ``core.image_quality``, or are one image
    twice, or None). ``check``: the recipe's ``camera.image_check``."""
    if not isinstance(item, StereoFrame) or frame_problem(item) is not None:
        return None, None  # inspect_frame names those
    repeated = repeats.problem(item)
    if repeated is not None:
        return repeated, None
    limits = check.min_mean_grey, check.max_saturated, check.min_texture
    left = image_problem(image_stats(item.left), *limits)
    if left is not None:
        return None, left
    if np.array_equal(item.left, item.right):
        # two sensors differ by their noise at least: one buffer handed over as both eyes shows no depth, and a
        # part without defects would pass unchecked for where its plate lies
        return None, ("the left and right images are the same, byte for byte: the camera delivers one eye's image "
                      "as both")
    return None, image_problem(image_stats(item.right), *limits, image="the right image")


class StageFailed(Exception):
    """A failure already described (a detection that ran ahead of its frame, a plugin's broken contract)."""


class StoreFailed(Exception):
    """The results store could not record a part, which went to the outputs all the same: the run stops."""


class CameraFailed(Exception):
    """The camera delivered something no part can be named from (``core.checks.delivery_problem``): the run
    stops, as for a camera that raises, rather than take it for the end of its frames."""


def _filter(detections: list[Detection], confidence: float, classes: list[str] | None) -> list[Detection]:
    return [d for d in detections if d.confidence >= confidence and (classes is None or d.class_name in classes)]


@dataclass
class RunSummary:
    run_id: int
    counts: Counter
    alarms: list[Alarm]
    frames: int
    elapsed_s: float
    stage_seconds: dict[str, float]
    interrupted: bool = False
    signal: int | None = None  # the signal that stopped the run (SIGTERM, SIGHUP), None for Ctrl-C or none

    @property
    def fps(self) -> float:
        return self.frames / self.elapsed_s if self.elapsed_s > 0 else 0.0

    @property
    def exit_code(self) -> int:
        if self.interrupted:
            return 128 + self.signal if self.signal else EXIT_INTERRUPTED
        if self.alarms:
            return EXIT_ALARMS
        if self.counts[Status.ERROR]:
            return EXIT_PART_ERRORS
        return EXIT_OK


def run(
    loaded: LoadedRecipe,
    registry: Registry | None = None,
    on_part: Callable[[FrameOutcome], None] | None = None,
    on_event: Callable[[OutputEvent | Alarm], None] | None = None,
    device: str = "auto",
    max_frames: int | None = None,
    on_start: Callable[[Pipeline], None] | None = None,
    stop_requested: Callable[[], int | None] | None = None,
) -> RunSummary:
    """Inspect every part the camera delivers. ``stop_requested()`` is asked after each part; a signal
    number stops the run there as Ctrl-C does (queued rejects delivered or alarmed, the ready coil dropped,
    the run finalised), with exit code 128 + that number."""
    registry = registry or default_registry()
    recipe = loaded.recipe
    apply_threads(recipe.threads)
    results = loaded.resolve(recipe.results.path)
    problem = store_problem(results)  # before any plugin opens its hardware
    if problem is not None:
        raise SetupError(loaded.describe(("results", "path"), problem))
    pipeline = build_pipeline(loaded, registry, device)
    check_stereo_memory(loaded, pipeline.stereo, registry)
    try:
        store = ResultsStore(results)
    except StoreError as exc:
        raise SetupError(loaded.describe(("results", "path"), str(exc))) from None
    try:  # the schema reads, but a page further in may not
        unfinished = store.unfinished_runs()
        run_id = store.start_run(recipe.name, loaded.text_hash, str(loaded.path), _sha256_or_none(loaded.path),
                                 _model_hashes(loaded, pipeline.detector),
                                 [getattr(output, "name", name) for name, output in pipeline.outputs])
    except sqlite3.DatabaseError as exc:
        raise SetupError(loaded.describe(("results", "path"), str(damaged(store.path, exc)))) from None
    age_limit = frame_age_limit_s(loaded, registry)
    rule = DepthRule.from_recipe(recipe)
    images = PartImages(store.image_dir, recipe.results.save_images, recipe.results.min_free_mb)
    counts: Counter = Counter()
    alarms: list[Alarm] = []
    stage_seconds: Counter = Counter()
    frames = 0
    interrupted = False
    stopped_by = None

    # the results store's first failure (a full or dead disk): from then on nothing more is written to it
    store_down: list[Exception] = []

    def record(events: list[OutputEvent | Alarm]) -> None:
        """Tell the operator, count the alarms, then store: a store that hangs or fails (a dead disk) must not
        keep an alarm from being heard, nor the run from closing its outputs."""
        for e in events:
            if isinstance(e, Alarm):
                alarms.append(e)
            if on_event:
                try:
                    on_event(e)
                except Exception:  # the operator's display gone (a closed pipe): the store must still hear of it
                    pass
        if store_down:
            return
        try:
            store.record_events(run_id, events)
        except Exception as exc:
            lose_store(exc)

    def lose_store(exc: Exception) -> None:
        store_down.append(exc)
        record([Alarm("store", f"results store failed ({type(exc).__name__}: {exc}): nothing more is recorded; the "
                               "parts already decided still go to the outputs, then the run stops", time.time(),
                      None, "store")])

    # called from the watch's thread while this one is stuck: the outputs first (the line must hear it even
    # if what follows hangs), then the operator and the store (whose writes take turns)
    def stalled(key: str, what: str, seconds: float) -> None:
        alarm = Alarm("engine", f"{what} after {seconds:.1f} s (watchdog_s: {recipe.watchdog_s:g}): a stage or plugin "
                      "is not returning; the outputs tell the line the inspection is not ready until it does",
                      time.time(), None if key == CAMERA_WAIT else key, "stall")
        _tell_outputs(pipeline, "hold", alarm.message)
        record([alarm])

    def resumed(seconds: float) -> None:
        _tell_outputs(pipeline, "release")
        record([OutputEvent("engine", None, "inspection running again", "delivered", time.time(),
                            f"after {seconds:.1f} s stalled; the outputs tell the line it is ready")])

    # runs that never finished (the process was killed, the power cut): their rejects may not have fired
    record(store.recover_crashed(unfinished, run_id))

    try:
        pipeline.warm_up()
        verified = _verify(loaded, registry, pipeline, rule, device)
    except KeyboardInterrupt:  # before the first plate: the run still closes its outputs and is finalised
        interrupted, verified = True, None
    if verified is not None:
        record([verified])
    if on_start:
        on_start(pipeline)
    started = time.perf_counter()
    failed_in_a_row = unusable_in_a_row = 0
    repeats = RepeatedImages()
    elsewhere = SurfaceElsewhere(recipe.stereo)

    def part_id(item: StereoFrame | FrameError) -> str:
        return f"R{run_id}-{item.index:06d}" + (f"+{item.slot}" if isinstance(item, UnreadFrame) else "")

    watch = StallWatch(recipe.watchdog_s, stalled, resumed).start()
    # a camera that runs free (it states a frame rate) owes a frame every period: a wait of watchdog_s is
    # a driver that stopped returning; one triggered by the parts may wait as long as the line stands
    rate = camera_answer(loaded, registry, "frame_rate")
    unread = UnreadFrames(rate)
    steps = ClockSteps()  # the system clock set while a frame is inspected: its reject timed on the new clock

    def watched(frames):
        """The camera's frames, each timed from when it is read; a free-running camera's waits too."""
        frames = iter(frames)
        first = True
        while True:
            if rate:
                # a slow camera may take three of its periods; opening one (an SDK's start) longer still
                wait = max(recipe.watchdog_s, 3.0 / rate, CAMERA_OPEN_S if first else 0.0)
                watch.started(CAMERA_WAIT, f"no frame from the camera (it runs at {rate:g} frames a second)", wait)
            first = False
            try:
                item = next(frames, _END)
            finally:
                if rate:
                    watch.finished(CAMERA_WAIT)
            if item is _END:
                return
            if (problem := delivery_problem(item)) is not None:  # a None was taken for the end: exit 0, parts unseen
                raise CameraFailed(problem)
            steps.arrived(part_id(item))
            watch.started(part_id(item), f"frame {item.frame_id} still in inspection")
            yield item

    # a line whose master parts passed a defective one reads no plate: its run ends here, with the alarm
    frames_in = watched(iter(()) if interrupted or isinstance(verified, Alarm) else pipeline.camera.frames())
    source = (DetectAhead(frames_in, lambda item: detect_frame(item, pipeline, recipe), max_frames)
              if recipe.stereo.concurrent else OneAtATime(frames_in, max_frames))

    in_hand: list = []  # the frames read and not yet decided: one the run leaves unfinished is rejected, never lost
    # [part, the outputs it has still to reach, the one being handed it]: an interrupt in between still
    # reaches the rest, and the one it interrupted raises an alarm
    handing: list = []

    def finish(outcome: FrameOutcome) -> None:
        """Store the part, then hand it to the outputs. A store that fails does not keep a decided part's reject
        from the actuator: it is handed over unrecorded (and the loop stops the run)."""
        part = outcome.part
        if not store_down:
            alarm = images.save(outcome.image, part, outcome.defect_status)
            if alarm is not None:
                record([alarm])
        if not store_down:  # recording that alarm may have found the store down
            try:
                store.record_part(run_id, part, outcome.per_defect)
            except Exception as exc:
                lose_store(exc)
        if in_hand and in_hand[0].frame_id == part.frame_id and in_hand[0].index == part.index:
            in_hand.pop(0)  # stored (or the store is gone): from here on it is a decided part, whatever stops the run
        counts[part.verdict.status] += 1
        handing[:] = [part, list(pipeline.outputs), None]
        hand_to_outputs()
        watch.finished(part.part_id)

    def hand_to_outputs() -> None:
        part, waiting, _ = handing
        step = steps.since(part.part_id)
        while waiting:
            name, output = waiting.pop(0)
            handing[2] = name
            try:
                # its own copy: an output that changed the part (its verdict, say) would change it for the
                # outputs after it and for the operator page; its capture time on the clock as it now stands
                sent = copy.deepcopy(part)
                sent.timestamp += step
                output.submit(sent)
            except Exception as exc:
                record([Alarm(name, f"reject output failed for {part.part_id}: {exc}", time.time(), part.part_id)])
            handing[2] = None
            try:
                reports = output.poll()
            except Exception as exc:  # one output's glitch must not stop the line, nor keep the part from the rest
                reports = [Alarm(name, f"asking the output what it sent failed after {part.part_id}: "
                                       f"{type(exc).__name__}: {exc}; what it had to report is lost", time.time(),
                                 part.part_id)]
            record(output_reports(name, reports, part.part_id))
        handing.clear()
        steps.forget(part.part_id)

    try:
        for item, detected in source:
            # the frames a free-running camera captured while the loop was busy are plates that went by unseen
            in_hand[:] = unread.between(item) + [item]
            for missed in in_hand[:-1]:
                steps.arrived(part_id(missed))  # stamped on the clock as it stands now
                finish(missed_outcome := inspect_frame(missed, part_id(missed), pipeline, loaded, rule))
                if on_part:
                    on_part(missed_outcome)
            if (alarm := unread.alarm(part_id(item))) is not None:
                record([alarm])
            repeated, unusable = frame_refusal(item, repeats, recipe.camera.image_check)
            # its age on the clock as it stood when the frame arrived (the camera stamped it on that one)
            outcome = inspect_frame(item, part_id(item), pipeline, loaded, rule, detected, age_limit,
                                    clock=steps.clock_at_arrival(part_id(item)), refused=repeated or unusable)
            part = outcome.part
            # One bad frame is that part's ERROR; several in a row mean the camera is lost, which
            # the operator must hear about once per outage, not once per frame.
            failed_in_a_row = failed_in_a_row + 1 if isinstance(item, FrameError) else 0
            if failed_in_a_row == CAMERA_LOST_AFTER:
                record([Alarm("camera", f"camera lost: {CAMERA_LOST_AFTER} frames in a row could not be captured "
                                        f"(last: {item.message}); parts are rejected as ERROR until frames arrive",
                              time.time(), part.part_id)])
            # a repeated image is never noise: the first one is a stalled camera the operator must hear of
            if repeated and repeats.run == 1:
                record([Alarm("camera", f"camera frozen: frame {item.frame_id}: {repeated}; parts are rejected as "
                                        f"ERROR until its images change", time.time(), part.part_id, "frozen")])
            unusable_in_a_row = unusable_in_a_row + 1 if unusable else 0
            if unusable_in_a_row == CAMERA_LOST_AFTER:
                record([Alarm("camera", f"images unusable: {CAMERA_LOST_AFTER} frames in a row (last: frame "
                                        f"{item.frame_id}: {unusable}); parts are rejected as ERROR until they "
                                        f"show the plate", time.time(), part.part_id, "image")])
            record(elsewhere.alarms(part, outcome.plate))
            finish(outcome)
            stage_seconds.update(outcome.timings)
            frames += 1
            if on_part:
                on_part(outcome)
            if store_down:
                raise StoreFailed(f"{part.part_id} ({part.verdict.status.value}) went to the outputs unrecorded")
            # a stop reads no new frame; the frames already read (detect-ahead's next) are still inspected
            if not interrupted and stop_requested is not None and (stopped_by := stop_requested()):
                interrupted = True
                source.stop_reading()
    except KeyboardInterrupt:
        interrupted = True
    except Exception as exc:  # a camera that raises instead of reporting a FrameError: stop, loudly
        record([Alarm("engine", f"run stopped after {frames} parts: {type(exc).__name__}: {exc}", time.time())])
    finally:
        watch.close()  # what follows may wait for a camera to stop (a part no longer in inspection)
        try:
            if handing:  # interrupted while a stored part was handed to the outputs
                part, _, interrupted_output = handing
                if interrupted_output is not None:
                    record([Alarm(interrupted_output, f"the run was interrupted while {part.part_id} "
                                  f"({part.verdict.status.value}) was handed to this output: it may not have received "
                                  f"it", time.time(), part.part_id)])
                    handing[2] = None
                hand_to_outputs()
            left = source.close()
            unfinished = in_hand + [item for item, _ in left]
            for item in unfinished:
                message = f"frame {item.frame_id}: not inspected: the run stopped first"
                try:
                    finish(FrameOutcome(PartResult(part_id(item), item.frame_id, item.index, item.timestamp,
                                                   error_verdict(message), error=message), [], None))
                except Exception as exc:  # the store or an output failing now must not skip closing them
                    record([Alarm("engine", f"{message}, and it could not be rejected: {type(exc).__name__}: {exc}",
                                  time.time())])
        except KeyboardInterrupt:  # a second Ctrl-C must not skip closing the outputs and the store
            interrupted = True
        elapsed = time.perf_counter() - started
        for name, output in pipeline.outputs:
            try:
                record(output_reports(name, output.close(), None))
            except KeyboardInterrupt:  # the next outputs and the store must still be closed
                interrupted = True
                record([Alarm(name, "closing was interrupted (Ctrl-C): commands it still held may not have been "
                              "sent", time.time())])
            except Exception as exc:
                record([Alarm(name, f"closing output failed: {exc}", time.time())])
        pipeline.close()
    summary = RunSummary(run_id, counts, alarms, frames, elapsed, dict(stage_seconds), interrupted, stopped_by)
    if not store_down:
        try:
            store.finish_run(run_id, counts, len(alarms), summary.fps, summary.exit_code)
        except Exception as exc:
            lose_store(exc)
    try:
        store.close()
    except Exception:
        pass  # a store that failed has said so
    return summary


def _verify(loaded: LoadedRecipe, registry: Registry, pipeline: Pipeline, rule: DepthRule, device: str
            ) -> OutputEvent | Alarm | None:
    """The recipe's master parts (``verify.path``) inspected as the line inspects its plates, their verdicts
    going nowhere but here (``core.verification``): an event with their tally, an alarm where a defective one
    passed or they could not be inspected (the run then reads no plate), None without master parts."""
    from core import verification

    if loaded.recipe.verify.path is None:
        return None
    folder = loaded.resolve(loaded.recipe.verify.path)
    try:
        camera = make_plugin(loaded, registry, plugin_context(loaded, device), "camera", "replay", "verify.path",
                             {"path": str(folder)})
        masters = Pipeline(camera, pipeline.stereo, pipeline.detector, [])

        def inspected(item):
            outcome = inspect_frame(item, f"master-{item.frame_id}", masters, loaded, rule)
            return outcome.part.verdict, [(m.detection.box, status) for m, status in
                                          zip(outcome.part.measurements, outcome.defect_status)]

        try:
            checked = verification.verify(folder, camera.frames(), inspected, loaded.recipe.decision)
        finally:
            camera.close()
    except Exception as exc:  # an unreadable recording vouches for nothing: the line does not start on it
        raise_if_interrupted(exc)
        return Alarm("verify", f"master parts {folder} could not be inspected ({exc}): the run does not start",
                     time.time(), None, "verify")
    if checked.failed:
        return Alarm("verify", checked.refusal(), time.time(), None, "verify")
    return OutputEvent("verify", None, "master parts", "delivered", time.time(), checked.summary())


def output_reports(name: str, reports: Any, part_id: str | None) -> list[OutputEvent | Alarm]:
    """What output ``name``'s ``poll`` or ``close`` returned (after the part ``part_id``, where one), less what
    breaks the contract (``core.checks.event_problem``), for which an alarm naming the output stands instead:
    the store, failing to write it, would take itself for broken and stop the line."""
    if not isinstance(reports, list):
        return [Alarm(name, f"the output reported a {type(reports).__name__}, not a list of events and alarms: what it "
                            f"had to report is lost", time.time(), part_id)]
    problems = [event_problem(e) for e in reports]
    kept = [e for e, problem in zip(reports, problems) if problem is None]
    wrong = [problem for problem in problems if problem is not None]
    if wrong:
        more = f" (and {len(wrong) - 1} more)" if len(wrong) > 1 else ""
        kept.append(Alarm(name, f"the output reported {wrong[0]}{more}: left out, what it meant is lost", time.time(),
                          part_id))
    return kept


def _tell_outputs(pipeline: Pipeline, what: str, *args: Any) -> None:
    """Call the optional ``hold``/``release`` of each output that has it; one failing must not stop the rest
    (the alarm says the inspection stalled either way)."""
    for _, output in pipeline.outputs:
        method = getattr(output, what, None)
        if callable(method):
            try:
                method(*args)
            except Exception:
                pass


def _sha256_or_none(path) -> str | None:
    try:
        return file_sha256(path)
    except OSError:
        return None


def _model_hashes(loaded: LoadedRecipe, detector: Any) -> dict[str, str]:
    """SHA-256 of the weights the run's detector loaded: which model made each verdict."""
    path = getattr(detector, "weights_path", None)
    if path is None and loaded.recipe.detector.weights is not None:
        path = loaded.resolve(loaded.recipe.detector.weights)
    digest = None if path is None else _sha256_or_none(path)
    return {} if digest is None else {str(path): digest}
