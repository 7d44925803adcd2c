"""``inspect eval depth``: the engine's stereo and depth on labelled sequences, against their truth.

For every labelled defect of every frame the engine's own stages run as on the line (the recipe's
stereo backend, region and range; ``core.depth.measure_frame``; ``core.decision``) with the true box
as the detection, so the figures measure stereo and depth alone. Each defect is measured twice on
the same disparity: with the recipe's ``depth.method`` and with ``disparity`` (the backend alone),
the reference.

The physical floor of a defect is what any estimator fitting the two surfaces to that pair could
reach: the disparity standard deviation ``sigma_noise * sqrt(2) / sqrt(sum I_x^2)`` over the
defect's region and over its ring, each of their pixels the right camera sees (I_x the left image's
horizontal gradient, sigma_noise the sensor noise the generator added, from the labels), the two
combined in quadrature and converted to mm at the defect's distance (``Z^2 / (f * B)`` mm per px). The
median and p90 of |error| such an estimator would show are the quantiles of the mixture of the defects'
normal errors. The distance's floor is the region's alone: the defect's distance is its own disparity's,
whatever the surface around it.

That floor takes ``sum I_x^2`` from the noisy image, so it counts the noise's own gradient energy
(``sigma_noise^2 / 2`` a pixel for the central difference) as texture. Where the texture is faint that is a
good part of the sum, and no estimator reaches that floor: the report also gives the texture's floor, the
same with the noise's expected share taken out of the sum.
"""
from __future__ import annotations

import json
import math
import time
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from core.boxes import MATCH_IOU, box_placement, match_boxes, shifts_beyond
from core.decision import CLEAR_CUT_MM, judge_defect, rule_applies
from core.depth import DepthRule, _clip_box, measure_frame, ring_mask, roi_box
from core.engine import StageFailed, disparity_range, frame_disparity, kept_detections
from core.error_parts import error_parts, true_ring_plane
from core.plate_view import plate_elsewhere
from core.recipe import LoadedRecipe
from core import uncertainty_budget
from core.report_text import decided, number, percent
from core.surface_fit import gradient_x, to_grey
from core.types import Detection, DefectMeasurement, Status, StereoFrame
from drivers.file_writes import write_text
from drivers.sequence_folder import SequenceError, read_disparity_png

NARROW_PX = 30.0  # boxes narrower than this count as narrow defects
MIN_RATIO_MM = 0.3  # measured / true only for defects at least this deep
MISSED = "missed"  # the outcome of a labelled defect the detector did not box
TRUE_PLANE_TOLERANCE_PX = 0.01  # a true disparity's pixels on its plane: KITTI PNGs round to 1/256 px
HALF_NORMAL_MEDIAN = 0.6745  # the median of |e| for a normal e of unit standard deviation


@dataclass
class DefectRow:
    """One labelled defect: its truth, both measurements, its floor and the decisions."""

    sequence: str
    frame_id: str
    cls: str
    box: tuple[float, float, float, float]
    true_distance_mm: float | None  # labels may give the deviation alone
    true_deviation_mm: float
    floor_mm: float | None
    method: str = ""
    distance_mm: float | None = None
    deviation_mm: float | None = None
    distance_sigma_mm: float | None = None
    deviation_sigma_mm: float | None = None
    reference_distance_mm: float | None = None
    reference_deviation_mm: float | None = None
    note: str = ""
    true_status: str = ""
    status: str = ""
    reference_status: str = ""
    proven: str = ""  # PASS, REJECT (proven beyond the guard band), undecided, or ERROR
    reference_proven: str = ""
    plain: str = ""  # the value against the limit, no guard band (as a decision without uncertainty would go)
    reference_plain: str = ""
    clear_cut: bool = False
    distance_floor_mm: float | None = None  # the floor of the distance (the region's alone)
    texture_floor_mm: float | None = None  # both floors from the texture's gradient energy alone
    texture_distance_floor_mm: float | None = None
    # the deviation's error in its three parts (``core.error_parts``), where the sequence has a true disparity
    error_ring_mm: float | None = None
    error_region_mm: float | None = None
    error_extent_mm: float | None = None
    # the box measured in against the true one (``core.boxes.box_placement``): its centre's offset as a share of
    # the defect's size, and its size over the defect's; None for a defect the detector missed
    box_shift: float | None = None
    box_scale: float | None = None
    # the largest part of the deviation's uncertainty (``core.uncertainty_budget.KINDS``), '' without an account
    uncertainty_from: str = ""

    @property
    def width_px(self) -> float:
        return min(self.box[2] - self.box[0], self.box[3] - self.box[1])


@dataclass
class Summary:
    defects: int
    measured: int
    deviation_error_mm: dict[str, float] = field(default_factory=dict)  # median, p90, max
    distance_error_mm: dict[str, float] = field(default_factory=dict)
    distance_error_percent: dict[str, float] = field(default_factory=dict)
    ratio_median: float | None = None
    narrow_ratio_median: float | None = None
    floor_mm: dict[str, float] = field(default_factory=dict)  # median, p90 of |error| at the floor
    error_over_floor: dict[str, float] = field(default_factory=dict)
    # each defect's |error| over its own floor, their median over the floor's own (HALF_NORMAL_MEDIAN): 1 at
    # the floor whatever the set's mix of floors, where a set's median error follows its few largest floors
    error_over_floor_per_defect: float | None = None
    distance_over_floor_per_defect: float | None = None  # likewise for the distance, against its own floor
    within_2_sigma: float | None = None
    distance_within_2_sigma: float | None = None  # the distance's errors within 2 of its reported sigma
    sigma_over_floor_median: float | None = None
    # the same three against the texture's floor, and how much higher than the floor that lies (median)
    error_over_texture_floor_per_defect: float | None = None
    distance_over_texture_floor_per_defect: float | None = None
    sigma_over_texture_floor_median: float | None = None
    texture_floor_over_floor_median: float | None = None
    # true outcome -> what the measurement proved (PASS, REJECT, undecided, ERROR) -> count
    confusion: dict[str, dict[str, int]] = field(default_factory=dict)
    clear_cut_wrong: int = 0
    clear_cut_wrong_beyond_2_sigma: int = 0
    clear_cut_silent_pass: int = 0
    clear_cut_wrong_plain: int = 0  # decided on the value alone, without the guard band
    missed: int = 0  # labelled defects the detector did not box (``--boxes detector``)
    missed_beyond_a_limit: int = 0  # ... of them, those whose truth rejects
    # where the boxes measured in lie (``DefectRow.box_shift``, ``box_scale``): the shift's median, p90 and max,
    # the scale's min and max, and how many lie more than HELD_SHIFT and UNSAFE_SHIFT off
    box_shift: dict[str, float] = field(default_factory=dict)
    box_scale: dict[str, float] = field(default_factory=dict)
    boxes_beyond: dict[str, int] = field(default_factory=dict)
    # the error's parts (``core.error_parts``): over how many defects; each part's median and p90 of |part| (mm)
    # and its share of the parts' summed squares
    error_parts: dict[str, Any] = field(default_factory=dict)
    # of the defects the measurement left undecided: the largest part of their uncertainty -> their true outcome ->
    # count (what would let more of them be decided)
    undecided_from: dict[str, dict[str, int]] = field(default_factory=dict)


def floor_px(grey: np.ndarray, mask: np.ndarray, noise_sigma: float, texture_only: bool = False,
             gradient: np.ndarray | None = None) -> float:
    """The disparity standard deviation of a region at the noise floor: sigma * sqrt(2) / sqrt(sum I_x^2) over the
    HxW bool ``mask``; ``texture_only``: the sum less the noise's expected share, sigma^2 / 2 a pixel (inf where
    nothing is left: a texture the noise hides). ``gradient``: ``gradient_x(grey)``, where the caller has it."""
    energy = float(np.sum((gradient_x(grey) if gradient is None else gradient)[mask] ** 2))
    if texture_only:
        energy -= np.count_nonzero(mask) * noise_sigma**2 / 2
    return noise_sigma * math.sqrt(2.0) / math.sqrt(energy) if energy > 0 else math.inf


def defect_floors_mm(grey: np.ndarray, box, calib, rule: DepthRule, noise_sigma: float, distance_mm: float,
                     texture_only: bool = False, gradient: np.ndarray | None = None) -> tuple[float, float]:
    """The floors of one defect's deviation and of its distance, in mm (module docstring; ``floor_px``)."""
    gradient = gradient_x(grey) if gradient is None else gradient
    shape = grey.shape
    region = np.zeros(shape, bool)
    x0, y0, x1, y1 = _clip_box(roi_box(box, rule), shape)
    region[y0:y1, x0:x1] = True
    ring = ring_mask(shape, box, rule.ring_gap_px, rule.ring_width_px)
    # a pixel the right camera does not see (left of the disparity) is one no estimator can match
    seen = np.arange(shape[1]) >= float(calib.disparity_px(distance_mm))
    region &= seen
    ring &= seen
    on_region = floor_px(grey, region, noise_sigma, texture_only, gradient)
    mm_per_px = distance_mm**2 / (calib.focal_px * calib.baseline_mm)
    return (math.hypot(on_region, floor_px(grey, ring, noise_sigma, texture_only, gradient)) * mm_per_px,
            on_region * mm_per_px)


def true_measurement(detection: Detection, truth: dict) -> DefectMeasurement:
    """The labels as a measurement without uncertainty, for the decision the truth calls for."""
    return DefectMeasurement(detection, truth.get("distance_mm"), truth["deviation_mm"], 1.0, 0.0, None,
                             distance_sigma_mm=0.0, deviation_sigma_mm=0.0, method="truth")


def distance_at_box(distance_mm: float, true_disparity: np.ndarray, calib, true_box, box, rule: DepthRule
                    ) -> float | None:
    """The true distance where ``box`` looks, a box off its defect's ``true_box``: the labels give the defect's
    distance at the true box's centre, and on a tilted plate another centre looks at the surface elsewhere. The
    plane of ``true_disparity`` (HxW px, NaN unknown) over the true box's ring moves it there; None where that
    ring has too few known pixels, or the moved disparity lies behind the camera."""
    plane = true_ring_plane(true_disparity, true_box, rule, TRUE_PLANE_TOLERANCE_PX)
    if plane is None:
        return None
    du = (box[0] + box[2] - true_box[0] - true_box[2]) / 2
    dv = (box[1] + box[3] - true_box[1] - true_box[3]) / 2
    moved = float(calib.disparity_px(distance_mm)) + plane.a * du + plane.b * dv
    return float(calib.distance_mm(moved)) if moved + calib.doffs > 0 else None


def clear_cut(truth: dict, recipe) -> bool:
    """True when the defect's true value is at least CLEAR_CUT_MM from every depth limit that applies to it."""
    for rule in recipe.decision.rules:
        if not rule_applies(rule, truth["class"]) or rule.quantity not in ("deviation_mm", "distance_mm"):
            continue
        value = truth.get(rule.quantity)
        if value is None or abs(value - rule.threshold) < CLEAR_CUT_MM:
            return False
    return True


@dataclass(frozen=True)
class BoxError:
    """What a detector does to a true box: its sides scaled about its centre by ``scale``, and the box moved
    by ``shift`` of its width and height in a direction drawn per defect (the same for every run)."""

    scale: float = 1.0
    shift: float = 0.0

    def apply(self, box, key: str) -> tuple[float, float, float, float]:
        x0, y0, x1, y1 = (float(v) for v in box)
        w, h = (x1 - x0) * self.scale, (y1 - y0) * self.scale
        angle = 2.0 * math.pi * (zlib.crc32(key.encode()) / 2**32)
        cx = (x0 + x1) / 2 + self.shift * (x1 - x0) * math.cos(angle)
        cy = (y0 + y1) / 2 + self.shift * (y1 - y0) * math.sin(angle)
        return cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2


def has_truth(defect: dict) -> bool:
    """Whether a labelled defect's truth gives a deviation to score against (its distance is scored where
    the labels give one too)."""
    return defect.get("deviation_mm") is not None


def evaluate_frame(frame: StereoFrame, labels: dict, loaded: LoadedRecipe, backend, sequence: str,
                   timings: list[tuple[float, float]], box_error: BoxError = BoxError(), detector=None
                   ) -> list[DefectRow]:
    """Every labelled defect of one frame (defects whose truth has no deviation are skipped), measured in
    the true boxes as ``box_error`` moves them, or with a ``detector`` in the box of its that matches the
    defect (``MATCH_IOU``; a defect without one is ``MISSED``); the floor is always the true box's, the true
    distance that where the box looks (``distance_at_box``; unscored without the frame's true disparity).
    Appends to ``timings`` the frame's depth seconds a defect, of the measurement and of the reference."""
    recipe = loaded.recipe
    rule = DepthRule.from_recipe(recipe)
    reference_rule = DepthRule.from_recipe(recipe, method="disparity")
    truths = [t for t in labels["defects"] if has_truth(t)]
    if not truths:
        return []
    true_boxes = [tuple(float(v) for v in t["box"]) for t in truths]
    if detector is None:
        detections = [Detection(t["class"], 1.0, box_error.apply(box, f"{sequence}/{frame.frame_id}/{i}"))
                      for i, (t, box) in enumerate(zip(truths, true_boxes))]
        boxed = detections
    else:
        # the stereo region covers every box the detector reports, as on the line
        detections = detected(detector, frame, recipe)
        found = match_boxes(np.array(true_boxes), np.array([d.box for d in detections]), MATCH_IOU)
        boxed = [None if j is None else detections[j] for j in found]
    rows = [missed_row(sequence, frame.frame_id, truth, box, recipe)
            for truth, box, det in zip(truths, true_boxes, boxed) if det is None]
    kept = [(truth, box, det) for truth, box, det in zip(truths, true_boxes, boxed) if det is not None]
    if not kept:
        return rows
    truths, true_boxes, boxed = (list(t) for t in zip(*kept))
    disparity = frame_disparity(backend, frame, recipe.stereo, detections, rule)
    start = time.perf_counter()
    measured = measure_frame(disparity, boxed, frame, rule, disparity_range(recipe.stereo, frame.calib))
    between = time.perf_counter()
    reference = measure_frame(disparity, boxed, frame, reference_rule)
    timings.append(((between - start) / len(boxed), (time.perf_counter() - between) / len(boxed)))
    grey = to_grey(frame.left)
    gradient = gradient_x(grey)  # every floor of the frame sums it
    noise = (labels.get("sensor") or {}).get("noise_sigma")
    # judged with uncertain: flag, a FLAG is a measurement that proved neither side of a limit
    undecided_as_flag = recipe.decision.model_copy(update={"uncertain": "flag"})
    no_band = recipe.decision.model_copy(update={"coverage_factor": 0.0})
    true_disparity = _true_disparity(frame)
    for det, box, truth, m, ref in zip(boxed, true_boxes, truths, measured, reference):
        # a set rendered without noise (``--noise-sigma 0``) has no noise floor to measure against; the floor's
        # pixels become millimetres at the true distance, or where the labels give none, at the measured one
        at = _first_known(truth.get("distance_mm"), m.distance_mm, ref.distance_mm)
        floor, distance_floor, texture_floor, texture_distance_floor = (
            (None,) * 4 if not noise or at is None else
            (*(_finite(f) for f in defect_floors_mm(grey, box, frame.calib, rule, noise, at, gradient=gradient)),
             *(_finite(f) for f in defect_floors_mm(grey, box, frame.calib, rule, noise, at, texture_only=True,
                                                    gradient=gradient))))
        # a groove's deviation is read on its band, not on the region the parts are of
        parts = (None if true_disparity is None or m.deviation_mm is None or m.distance_mm is None
                 or m.groove_angle_deg is not None else
                 error_parts(m.deviation_mm, m.distance_mm, truth["deviation_mm"], true_disparity, frame.calib, det.box,
                             rule, TRUE_PLANE_TOLERANCE_PX))
        shift, scale = box_placement([box], [det.box])
        if truth.get("distance_mm") is not None and _moved(det.box, box):
            # a box off its defect's centre measures the distance where it looks; without the true disparity
            # there is no truth for that point
            truth = {**truth, "distance_mm": None if true_disparity is None else distance_at_box(
                truth["distance_mm"], true_disparity, frame.calib, box, det.box, rule)}
        rows.append(DefectRow(
            sequence, frame.frame_id, truth["class"], box, truth.get("distance_mm"), truth["deviation_mm"], floor,
            m.method, m.distance_mm, m.deviation_mm, m.distance_sigma_mm, m.deviation_sigma_mm,
            ref.distance_mm, ref.deviation_mm, m.note,
            true_status=judge_defect(true_measurement(det, truth), recipe.decision)[0].value,
            status=judge_defect(m, recipe.decision)[0].value,
            reference_status=judge_defect(ref, recipe.decision)[0].value,
            proven=_proven(judge_defect(m, undecided_as_flag)[0]),
            reference_proven=_proven(judge_defect(ref, undecided_as_flag)[0]),
            plain=judge_defect(m, no_band)[0].value, reference_plain=judge_defect(ref, no_band)[0].value,
            clear_cut=clear_cut(truth, recipe), distance_floor_mm=distance_floor,
            texture_floor_mm=texture_floor, texture_distance_floor_mm=texture_distance_floor,
            **({} if parts is None else {"error_ring_mm": parts.ring_mm, "error_region_mm": parts.region_mm,
                                         "error_extent_mm": parts.extent_mm}),
            box_shift=float(shift[0]), box_scale=float(scale[0]),
            uncertainty_from=uncertainty_budget.largest_kind(m.uncertainty_parts),
        ))
    return rows


def _finite(value: float) -> float | None:
    """None for a floor that no texture bounds, or of pixels the right camera does not see (JSON has no
    infinity)."""
    return value if math.isfinite(value) else None


def _moved(box, true_box) -> bool:
    """Whether ``box``'s centre lies off ``true_box``'s (by more than rounding)."""
    return max(abs(float(box[i]) + float(box[i + 2]) - float(true_box[i]) - float(true_box[i + 2]))
               for i in (0, 1)) > 0.02


def _true_disparity(frame: StereoFrame) -> np.ndarray | None:
    """The frame's true disparity (HxW px, NaN unknown) where its sequence has one, else None; SequenceError
    naming the file where it is not a disparity PNG."""
    path = frame.meta.get("gt_disparity")
    if path is None or Path(path).suffix != ".png":
        return None
    truth = read_disparity_png(Path(path))
    if truth.shape != frame.left.shape[:2]:
        raise SequenceError(f"{path}: a true disparity of {truth.shape[1]}x{truth.shape[0]} px for images of "
                            f"{frame.left.shape[1]}x{frame.left.shape[0]}")
    return truth


def plate_check(frame: StereoFrame, recipe) -> dict[str, Any] | None:
    """What the engine's check of a part without defects (``core.plate_view``) says of ``frame`` at the
    recipe's working distance: None where it lets the part be decided, else where it sees the plate."""
    found = plate_elsewhere(frame.left, frame.right, frame.calib, disparity_range(recipe.stereo, frame.calib))
    if found is None:
        return None
    if found.unmatched or found.rows_apart:
        return {"distance_mm": None, "swapped": False, "unmatched": bool(found.unmatched), "rows_apart": found.rows_apart}
    return {"distance_mm": round(found.distance_mm, 1), "swapped": found.swapped, "unmatched": False, "rows_apart": 0}


def detected(detector, frame: StereoFrame, recipe) -> list[Detection]:
    """The detector's boxes on the frame's left image as the line keeps them (``engine.kept_detections``);
    a detector that breaks its contract is an error, not an empty frame."""
    try:
        found = detector.detect(frame.left)
    except Exception as exc:  # as on the line, where such a frame is an ERROR part: here it ends the evaluation
        raise StageFailed(f"frame {frame.frame_id}: detection failed: {type(exc).__name__}: {exc}") from None
    kept, problem = kept_detections(found, detector, recipe, frame.left.shape[:2])
    if problem is not None:
        raise StageFailed(f"frame {frame.frame_id}: {problem}")
    return kept


def missed_row(sequence: str, frame_id: str, truth: dict, box, recipe) -> DefectRow:
    """A labelled defect no box of the detector found: no measurement, and the outcome ``MISSED``."""
    det = Detection(truth["class"], 1.0, box)
    return DefectRow(sequence, frame_id, truth["class"], box, truth.get("distance_mm"), truth["deviation_mm"], None,
                     note="missed by the detector", true_status=judge_defect(true_measurement(det, truth),
                                                                             recipe.decision)[0].value,
                     status=MISSED, reference_status=MISSED, proven=MISSED, reference_proven=MISSED, plain=MISSED,
                     reference_plain=MISSED, clear_cut=clear_cut(truth, recipe))


def _proven(status: Status) -> str:
    return "undecided" if status is Status.FLAG else status.value


def _stats(values) -> dict[str, float]:
    a = np.asarray(list(values), dtype=np.float64)
    if a.size == 0:
        return {}
    return {"median": float(np.median(a)), "p90": float(np.percentile(a, 90)), "max": float(a.max())}


def mixture_quantile(sigmas: np.ndarray, q: float) -> float:
    """The q-quantile of |e| when e is normal with one of ``sigmas`` (each equally likely)."""
    from math import erf

    sigmas = sigmas[np.isfinite(sigmas) & (sigmas > 0)]
    if sigmas.size == 0:
        return math.nan

    def cdf(x: float) -> float:
        return float(np.mean([erf(x / (s * math.sqrt(2.0))) for s in sigmas]))

    lo, hi = 0.0, 10.0 * float(sigmas.max())
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cdf(mid) < q else (lo, mid)
    return 0.5 * (lo + hi)


def summarise(rows: list[DefectRow], reference: bool = False) -> Summary:
    """The figures of a set of rows, for the measurement (or, ``reference``, for the backend alone)."""
    dev = "reference_deviation_mm" if reference else "deviation_mm"
    dist = "reference_distance_mm" if reference else "distance_mm"
    ok = [r for r in rows if getattr(r, dev) is not None]
    s = Summary(len(rows), len(ok))
    s.deviation_error_mm = _stats(abs(getattr(r, dev) - r.true_deviation_mm) for r in ok)
    with_distance = [r for r in rows if getattr(r, dist) is not None and r.true_distance_mm is not None]
    s.distance_error_mm = _stats(abs(getattr(r, dist) - r.true_distance_mm) for r in with_distance)
    s.distance_error_percent = _stats(100 * abs(getattr(r, dist) - r.true_distance_mm) / r.true_distance_mm
                                      for r in with_distance)
    deep = [r for r in ok if abs(r.true_deviation_mm) >= MIN_RATIO_MM]
    if deep:
        s.ratio_median = float(np.median([getattr(r, dev) / r.true_deviation_mm for r in deep]))
    narrow = [r for r in deep if r.width_px < NARROW_PX]
    if narrow:
        s.narrow_ratio_median = float(np.median([getattr(r, dev) / r.true_deviation_mm for r in narrow]))
    floors = np.array([r.floor_mm for r in rows if r.floor_mm is not None], dtype=np.float64)
    if floors.size:
        s.floor_mm = {"median": mixture_quantile(floors, 0.5), "p90": mixture_quantile(floors, 0.9)}
        if s.deviation_error_mm:
            s.error_over_floor = {k: s.deviation_error_mm[k] / s.floor_mm[k] for k in ("median", "p90")
                                  if s.floor_mm.get(k)}
    s.error_over_floor_per_defect = _per_defect([(abs(getattr(r, dev) - r.true_deviation_mm), r.floor_mm) for r in ok])
    s.distance_over_floor_per_defect = _per_defect([(abs(getattr(r, dist) - r.true_distance_mm), r.distance_floor_mm)
                                                    for r in with_distance])
    s.error_over_texture_floor_per_defect = _per_defect([(abs(getattr(r, dev) - r.true_deviation_mm),
                                                          r.texture_floor_mm) for r in ok])
    s.distance_over_texture_floor_per_defect = _per_defect([(abs(getattr(r, dist) - r.true_distance_mm),
                                                             r.texture_distance_floor_mm) for r in with_distance])
    both = [r.texture_floor_mm / r.floor_mm for r in rows if r.floor_mm and r.texture_floor_mm]
    if both:
        s.texture_floor_over_floor_median = float(np.median(both))
    if not reference:
        s.error_parts = parts_summary(ok)
        sig = [r for r in ok if r.deviation_sigma_mm]
        if sig:
            s.within_2_sigma = float(np.mean([abs(r.deviation_mm - r.true_deviation_mm) <= 2 * r.deviation_sigma_mm
                                              for r in sig]))
            with_sigma = [r for r in with_distance if r.distance_sigma_mm]
            if with_sigma:
                s.distance_within_2_sigma = float(np.mean([abs(r.distance_mm - r.true_distance_mm)
                                                           <= 2 * r.distance_sigma_mm for r in with_sigma]))
            with_floor = [r for r in sig if r.floor_mm]
            if with_floor:
                s.sigma_over_floor_median = float(np.median([r.deviation_sigma_mm / r.floor_mm for r in with_floor]))
            with_floor = [r for r in sig if r.texture_floor_mm]
            if with_floor:
                s.sigma_over_texture_floor_median = float(np.median([r.deviation_sigma_mm / r.texture_floor_mm
                                                                     for r in with_floor]))
    placed = [r for r in rows if r.box_shift is not None]
    if placed:
        s.box_shift = _stats(r.box_shift for r in placed)
        s.box_scale = {"min": min(r.box_scale for r in placed), "max": max(r.box_scale for r in placed)}
        s.boxes_beyond = dict(zip(("tenth", "third"), shifts_beyond(r.box_shift for r in placed)))
    missed = [r for r in rows if r.proven == MISSED]
    s.missed = len(missed)
    s.missed_beyond_a_limit = sum(r.true_status == Status.REJECT.value for r in missed)
    for r in rows:
        plain = r.reference_plain if reference else r.plain
        if r.clear_cut and plain in (Status.PASS.value, Status.REJECT.value) and plain != r.true_status:
            s.clear_cut_wrong_plain += 1
        proven = r.reference_proven if reference else r.proven
        s.confusion.setdefault(r.true_status, {}).setdefault(proven, 0)
        s.confusion[r.true_status][proven] += 1
        if not reference and proven == "undecided" and r.uncertainty_from:
            s.undecided_from.setdefault(r.uncertainty_from, {}).setdefault(r.true_status, 0)
            s.undecided_from[r.uncertainty_from][r.true_status] += 1
        # undecided ones go as the recipe's uncertain says: that is the decision working, not a wrong side
        if not r.clear_cut or proven not in (Status.PASS.value, Status.REJECT.value) or proven == r.true_status:
            continue
        s.clear_cut_wrong += 1
        if proven == Status.PASS.value:
            s.clear_cut_silent_pass += 1
        sigma = None if reference else r.deviation_sigma_mm
        value = getattr(r, dev)
        if value is not None and (sigma is None or abs(value - r.true_deviation_mm) > 2 * sigma):
            s.clear_cut_wrong_beyond_2_sigma += 1
    return s


PARTS = (("ring", "error_ring_mm"), ("region", "error_region_mm"), ("extent", "error_extent_mm"))


def parts_summary(rows: list[DefectRow]) -> dict[str, Any]:
    """The error's parts over the rows that have them: ``defects``, and per part (``PARTS``) the median and p90
    of its magnitude (mm) and its ``share`` of the parts' summed squares; empty without such rows."""
    with_parts = [r for r in rows if r.error_ring_mm is not None]
    if not with_parts:
        return {}
    values = {name: np.array([getattr(r, key) for r in with_parts]) for name, key in PARTS}
    total = sum(float(np.sum(x * x)) for x in values.values())
    return {"defects": len(with_parts),
            **{name: {"median": float(np.median(np.abs(x))), "p90": float(np.percentile(np.abs(x), 90)),
                      "share": float(np.sum(x * x)) / total if total > 0 else None}
               for name, x in values.items()}}


def _per_defect(pairs: list[tuple[float, float | None]]) -> float | None:
    """The median of each |error| over its own floor (pairs without a floor left out), over the floor's own
    median (HALF_NORMAL_MEDIAN): 1 at the floor."""
    standardised = [error / floor for error, floor in pairs if floor]
    return float(np.median(standardised)) / HALF_NORMAL_MEDIAN if standardised else None


def report(rows: list[DefectRow], meta: dict[str, Any], seconds_per_defect: float | None,
           reference_seconds_per_defect: float | None = None) -> dict[str, Any]:
    """The JSON report: settings, per sequence and pooled summaries (measurement and reference), the measurement's
    summary per class of the labels, rows; the depth time per defect of the measurement and of the reference."""
    sequences = sorted({r.sequence for r in rows})
    body: dict[str, Any] = {**meta, "seconds_per_defect": seconds_per_defect,
                            "reference_seconds_per_defect": reference_seconds_per_defect, "sequences": {}}
    for name in sequences:
        part = [r for r in rows if r.sequence == name]
        body["sequences"][name] = {"measurement": asdict(summarise(part)), "reference": asdict(summarise(part, True))}
    body["all"] = {"measurement": asdict(summarise(rows)), "reference": asdict(summarise(rows, True))}
    # a set's mix of classes hides one that reads short: a rule may be set per class
    body["classes"] = {name: asdict(summarise([r for r in rows if r.cls == name]))
                       for name in sorted({r.cls for r in rows})}
    body["rows"] = [{**asdict(r), "width_px": r.width_px} for r in rows]
    return body


def _fmt3(d: dict, keys=("median", "p90", "max"), digits: int = 3) -> str:
    return " / ".join(f"{d[k]:.{digits}f}" for k in keys if k in d) if d else "n/a"


def _distance_calibration(s: dict[str, Any]) -> str:
    share = s.get("distance_within_2_sigma")
    return "" if share is None else f" ({percent(share)})"


def markdown(body: dict[str, Any]) -> str:
    """The report as Markdown: one table row per sequence and the pooled row, measurement and reference."""
    moved = (f"; the true boxes scaled by {body['box_scale']:g} and moved by {body['box_shift']:g} of their size"
             if body.get("box_scale", 1.0) != 1.0 or body.get("box_shift", 0.0) else
             "; the detector's boxes" if body.get("boxes") == "detector" else "")
    lines = [
        f"Recipe `{body['recipe']}`, backend `{body['backend']}`, depth method `{body['method']}`{moved}; "
        f"machine: {body['machine']}",
        "",
        "| sequence | method | defects (measured) | deviation error mm, median / p90 / max | floor mm, median / p90 "
        "| error ÷ floor, median / p90 | error ÷ floor per defect | measured ÷ true (narrow) | within ±2σ | σ ÷ floor "
        "| distance error, median % of Z (within ±2σ) | distance error ÷ floor per defect "
        "| clear-cut on the wrong side (silent PASS) | clear-cut on the wrong side without the guard band |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    items = [*body["sequences"].items(), ("all", body["all"])]
    for name, entry in items:
        for label, key in ((body["method"], "measurement"), ("disparity (reference)", "reference")):
            s = entry[key]
            lines.append(
                f"| {name} | {label} | {s['defects']} ({s['measured']}) | {_fmt3(s['deviation_error_mm'])} | "
                f"{_fmt3(s['floor_mm'], ('median', 'p90'))} | {_fmt3(s['error_over_floor'], ('median', 'p90'), 2)} | "
                f"{number(s['error_over_floor_per_defect'])} | "
                f"{number(s['ratio_median'])} ({number(s['narrow_ratio_median'])}) | "
                f"{percent(s['within_2_sigma'])} | "
                f"{number(s['sigma_over_floor_median'])} | {number(s['distance_error_percent'].get('median'), 3)}"
                f"{_distance_calibration(s)} | {number(s['distance_over_floor_per_defect'])} | "
                f"{s['clear_cut_wrong']} ({s['clear_cut_silent_pass']}) | {s['clear_cut_wrong_plain']} |")
    classes = body.get("classes", {})
    if len(classes) > 1:
        lines += ["", f"By the labels' class ({body['method']}; narrow: boxes under {NARROW_PX:.0f} px):", "",
                  "| class | defects (measured) | measured ÷ true (narrow) | error ÷ floor per defect | within ±2σ "
                  "| σ ÷ floor | inside the limit: proven / undecided | beyond it: proven / undecided "
                  "| clear-cut on the wrong side (silent PASS) |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for name, s in classes.items():
            proven_pass, undecided_pass, proven_reject, undecided_reject = decided(s["confusion"])
            lines.append(
                f"| {name} | {s['defects']} ({s['measured']}) | {number(s['ratio_median'])} "
                f"({number(s['narrow_ratio_median'])}) | {number(s['error_over_floor_per_defect'])} | "
                f"{percent(s['within_2_sigma'])} | {number(s['sigma_over_floor_median'])} | "
                f"{proven_pass} / {undecided_pass} | {proven_reject} / {undecided_reject} | "
                f"{s['clear_cut_wrong']} ({s['clear_cut_silent_pass']}) |")
    pooled = body["all"]["measurement"]
    if pooled.get("texture_floor_over_floor_median") is not None:
        lines += ["", "The floor counts the noise's own gradient energy as texture (σ²/2 a pixel of Σ I_x²); without it, "
                  f"the texture's floor lies a median {pooled['texture_floor_over_floor_median']:.2f}x higher, and "
                  "against it, all sequences: error per defect "
                  f"{number(pooled['error_over_texture_floor_per_defect'])}, σ "
                  f"{number(pooled['sigma_over_texture_floor_median'])}, distance error per defect "
                  f"{number(pooled['distance_over_texture_floor_per_defect'])}."]
    parts = pooled.get("error_parts")
    if parts:
        lines += ["", f"Where the error comes from (the frames' true disparity, {parts['defects']} of the "
                  f"{pooled['measured']} measured defects; median / p90 of each part, mm, and its share of their "
                  "squares): " + ", ".join(
                      f"{label} {_fmt3(parts[name], ('median', 'p90'))} ({percent(parts[name]['share'])})"
                      for name, label in (("ring", "the ring's plane"), ("region", "the region's estimate"),
                                          ("extent", "the region's extent (its true mean against the labels)")))
                  + "; a defect read along a groove across its box has none (core/error_parts.py)."]
    lines += ["", "Decisions at the recipe's rules, all sequences: the true outcome against what the measurement proved "
              f"(undecided: within the guard band, resolved by the recipe's uncertain: {body['uncertain']}):", ""]
    confusion = body["all"]["measurement"]["confusion"]
    outcomes = sorted({o for row in confusion.values() for o in row} | set(confusion))
    lines.append("| true \\ measured | " + " | ".join(outcomes) + " |")
    lines.append("|---|" + "---|" * len(outcomes))
    for truth in sorted(confusion):
        lines.append(f"| {truth} | " + " | ".join(str(confusion[truth].get(o, 0)) for o in outcomes) + " |")
    undecided = body["all"]["measurement"].get("undecided_from")
    if undecided:
        lines += ["", "What the undecided defects' uncertainty mostly came from (the largest part of each one's, "
                  "core/uncertainty_budget.py; defects inside their limit / beyond it): "
                  + ", ".join(uncertainty_budget.tally_words(undecided)) + "."]
    if body.get("boxes") == "detector":
        s = body["all"]["measurement"]
        lines += ["", f"Boxes from the recipe's detector (`{body['detector']}`, confidence {body['confidence']:g}): "
                  f"{s['defects'] - s['missed']} of the {s['defects']} labelled defects boxed (IoU at least {MATCH_IOU:g}); "
                  f"{s['missed']} missed, {s['missed_beyond_a_limit']} of them beyond a limit (on the line their part "
                  "passes unless another box rejects it). The figures above are over the boxed ones."]
        if s.get("box_shift"):
            lines[-1] += (f" Its boxes lie a median {s['box_shift']['median']:.2f} of their defect's size off its "
                          f"centre (p90 {s['box_shift']['p90']:.2f}, at most {s['box_shift']['max']:.2f}), "
                          f"{s['boxes_beyond']['tenth']} more than a tenth and {s['boxes_beyond']['third']} more than a "
                          f"third off, at {s['box_scale']['min']:.2f}-{s['box_scale']['max']:.2f} of its size "
                          f"(docs/depth-conditions.md, boxes that are off).")
    if body.get("unscored"):
        lines += ["", f"Not scored: {body['unscored']} labelled defect(s) whose labels give no true deviation "
                  "(their truth could not be measured, as for a defect the right camera does not see)."]
    checked = body.get("plate_check")
    if checked:
        flagged = checked["flagged"]
        swapped = sum(1 for f in flagged if f["swapped"])
        unmatched = sum(1 for f in flagged if f.get("unmatched"))
        rows = sum(1 for f in flagged if f.get("rows_apart"))
        lines += ["", f"The check of a part without defects (each frame as if the detector found nothing): "
                  f"{len(flagged) - swapped - unmatched - rows} of {checked['frames']} frames show the plate outside "
                  f"the working distance, {swapped} only with the eyes swapped, {rows} only with the eyes' rows apart, "
                  f"{unmatched} with images that match nowhere (such a part is an ERROR)."]
    if body.get("seconds_per_defect") is not None:
        line = f"Depth per defect ({body['method']}): {1000 * body['seconds_per_defect']:.1f} ms on this machine"
        if body.get("reference_seconds_per_defect") is not None:
            # what the backend-only measurement costs without the check of where the plate lies, which the
            # line's `method: disparity` adds: the surface fit's own work is the rest
            line += (f"; the reference, the backend's plane and median alone, "
                     f"{1000 * body['reference_seconds_per_defect']:.1f} ms")
        lines += ["", line + "."]
    return "\n".join(lines) + "\n"


def _first_known(*distances: float | None) -> float | None:
    """The first of ``distances`` that is known: the true one, else the measured one, else the backend's."""
    return next((float(z) for z in distances if z is not None), None)


def _distance_of(r: DefectRow) -> float:
    """The defect's true distance, or where its labels give none, the measured one (NaN: not drawn)."""
    found = _first_known(r.true_distance_mm, r.distance_mm, r.reference_distance_mm)
    return math.nan if found is None else found


def figure(rows: list[DefectRow], path: Path) -> None:
    """|deviation error| against distance and against defect width, with each defect's floor."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r.deviation_mm is not None]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, key, label in ((axes[0], _distance_of, "distance mm"),
                           (axes[1], lambda r: r.width_px, "defect width px (shorter side of the box)")):
        ax.scatter([key(r) for r in ok], [abs(r.deviation_mm - r.true_deviation_mm) for r in ok], s=14,
                   label=f"{rows[0].method if rows else ''} |error|")
        ref = [r for r in rows if r.reference_deviation_mm is not None]
        ax.scatter([key(r) for r in ref], [abs(r.reference_deviation_mm - r.true_deviation_mm) for r in ref], s=10,
                   marker="x", alpha=0.6, label="disparity alone |error|")
        fl = [r for r in rows if r.floor_mm is not None]
        ax.scatter([key(r) for r in fl], [r.floor_mm for r in fl], s=10, marker="_", c="k", label="floor (1 σ)")
        ax.set_xlabel(label)
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("|deviation error| mm")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def save(body: dict[str, Any], rows: list[DefectRow], out: Path, with_figure: bool = True) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "depth_eval.json", out / "depth_eval.md"]
    write_text(written[0], json.dumps(body, indent=1, default=float))
    write_text(written[1], markdown(body))
    # a set in which nothing was measured (every defect missed or unavailable) has nothing to plot
    if with_figure and any(r.deviation_mm is not None or r.reference_deviation_mm is not None for r in rows):
        figure(rows, out / "depth_eval.png")
        written.append(out / "depth_eval.png")
    return written
