"""The recipe: what a quality engineer writes to describe one inspection.

Every section rejects unknown keys, so a typo is an error instead of a silently ignored setting.
Relative paths in a recipe are relative to the recipe file.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, ClassVar, Literal

from pydantic import ConfigDict, Field, field_validator, model_validator

from core.settings_model import Settings

if TYPE_CHECKING:
    from core.types import Calibration

QUANTITIES = ("deviation_mm", "distance_mm", "confidence", "area_mm2")
OPERATORS = (">", ">=", "<", "<=")


class Section(Settings):
    """One section of the recipe (or a part of one)."""


class PluginRef(Section):
    plugin: str = Field(min_length=1)
    settings: dict[str, Any] = Field(default_factory=dict)


class ImageCheck(Section):
    """What a frame's left image must show before its detections (or their absence) may decide the part
    (``core.image_quality``); a frame that fails is its part's ERROR. The defaults trip only on images
    with no usable content; 0, 1 and 0 turn each test off."""

    min_mean_grey: float = Field(20.0, ge=0, le=255)
    max_saturated: float = Field(0.9, ge=0, le=1)
    min_texture: float = Field(0.7, ge=0)


class CameraSection(PluginRef):
    # A frame that reaches inspection later than this after its capture is an ERROR, not a late reject;
    # by default the shortest time from the camera to an output's actuator (its part is past it by then).
    max_frame_age_ms: float | None = Field(None, gt=0)
    image_check: ImageCheck = Field(default_factory=ImageCheck)


class StereoSection(Section):
    backend: str = Field("torch_sgm", min_length=1)
    settings: dict[str, Any] = Field(default_factory=dict)
    min_disparity: float | None = Field(None, ge=0)
    max_disparity: float | None = Field(None, gt=0)
    working_distance_mm: tuple[float, float] | None = None
    scale: float = Field(1.0, gt=0.05, le=1.0)
    schedule: Literal["every_frame", "on_defect"] = "on_defect"
    # full: match the whole frame (the reference). defects: match only the rows and columns that the
    # detector's boxes, their depth ring and roi_margin_px need (plus the disparity search range to
    # the left), so a frame costs stereo in proportion to its defects (needs schedule: on_defect).
    region: Literal["full", "defects"] = "full"
    # the context around each needed rectangle, in image pixels; None: 16 of the matcher's pixels, and at
    # least 32 (``margin_px``), which is what crops need to give the full frame's depth
    roi_margin_px: int | None = Field(None, ge=0, le=1000)
    # Detect the next frame (in a second thread) while this frame's stereo, depth, decision and
    # outputs run. A part's verdict still uses its own frame's disparity.
    concurrent: bool = True

    @property
    def margin_px(self) -> int:
        """``roi_margin_px``, or where the recipe leaves it out, 16 of the matcher's pixels and at least 32."""
        return self.roi_margin_px if self.roi_margin_px is not None else max(32, math.ceil(16 / self.scale))

    @field_validator("working_distance_mm")
    @classmethod
    def _within_a_cameras_reach(cls, value):
        if value is not None and value[1] > cls.MAX_WORKING_DISTANCE_MM:
            raise ValueError(f"{value[1]:g} mm is farther than any stereo camera measures; at most "
                             f"{cls.MAX_WORKING_DISTANCE_MM:g} mm")
        return value

    @model_validator(mode="after")
    def _one_range(self) -> StereoSection:
        has_disp = self.min_disparity is not None or self.max_disparity is not None
        if has_disp and self.working_distance_mm is not None:
            raise ValueError("give either min_disparity/max_disparity or working_distance_mm, not both")
        if not has_disp and self.working_distance_mm is None:
            raise ValueError("give a disparity range (min_disparity, max_disparity) or working_distance_mm: [near, far]")
        if has_disp:
            if self.max_disparity is None:
                raise ValueError("max_disparity is required with min_disparity")
            if self.max_disparity <= (self.min_disparity or 0):
                raise ValueError("max_disparity must be larger than min_disparity")
        if self.working_distance_mm is not None:
            near, far = self.working_distance_mm
            if not 0 < near < far:
                raise ValueError("working_distance_mm must be [near, far] with 0 < near < far")
        if self.region == "defects" and self.schedule == "every_frame":
            raise ValueError("region: defects matches only around detections; it needs schedule: on_defect")
        return self

    RANGE_MARGIN_PX: ClassVar[int] = 2  # each side of a working distance's disparities
    MAX_WORKING_DISTANCE_MM: ClassVar[float] = 100_000.0  # five times the ZED's range

    def search_range(self, calib: Calibration) -> tuple[float, float]:
        """The disparities searched in full-resolution pixels (lo, hi): the working distance's with
        RANGE_MARGIN_PX each side, or min/max_disparity. ValueError where they do not fit the image."""
        if self.working_distance_mm is not None:
            near, far = self.working_distance_mm
            lo = max(0.0, math.floor(float(calib.disparity_px(far))) - self.RANGE_MARGIN_PX)
            hi = math.ceil(float(calib.disparity_px(near))) + self.RANGE_MARGIN_PX
        else:
            lo, hi = self.min_disparity or 0.0, self.max_disparity
        if hi >= calib.width:
            raise ValueError(f"stereo: disparity range up to {hi:g} px does not fit the {calib.width} px wide image")
        return lo, hi


class DetectorSection(Section):
    plugin: str = Field("yolov8", min_length=1)
    weights: str | None = None
    # the weights file's SHA-256 (64 hex digits): any other file is refused at validation
    sha256: str | None = Field(None, pattern=r"^[0-9a-fA-F]{64}$")
    confidence: float = Field(0.25, ge=0.0, le=1.0)
    classes: list[str] | None = None
    settings: dict[str, Any] = Field(default_factory=dict)

    @field_validator("classes")
    @classmethod
    def _some_class(cls, value):
        if value is not None and not value:
            raise ValueError("an empty list keeps no class: nothing would be detected and every part pass "
                             "(null keeps every class)")
        return value

    @field_validator("sha256", mode="before")
    @classmethod
    def _quoted(cls, value):
        if isinstance(value, int) and not isinstance(value, bool):
            raise ValueError("write the SHA-256 in quotes: YAML reads a hash of digits alone as a number")
        return value


class DepthSection(Section):
    # the box's central share measured as the defect: a larger one takes in the defect's walls and reads it
    # shallower than it is (on the evaluation sets 0.7 proved 2 of 633 defects inside a limit they lie beyond,
    # 0.8 one of 219, the whole box 2 of 78; docs/research-log.md), a smaller one costs only pixels
    inner_fraction: float = Field(0.6, gt=0.0, le=0.6)
    ring_gap_px: int = Field(3, ge=0, le=200)
    ring_width_px: int = Field(12, ge=2, le=200)
    # method surface: the ring's width where its texture is faint against the region's, whose plane then leads
    # the deviation's uncertainty (core.depth.ring_width; no wider than ring_width_px: never widened)
    faint_ring_width_px: int = Field(20, ge=2, le=200)
    min_valid_fraction: float = Field(0.10, ge=0.0, le=1.0)
    min_ring_points: int = Field(30, ge=3)
    min_plane_inliers: float = Field(0.6, gt=0.0, le=1.0)
    plane_tolerance_px: float = Field(1.0, gt=0.0)
    # the backend's disparity noise, the uncertainty of ``method: disparity``: a smaller one proves what the map
    # cannot tell (at 0.05 px 44 of the nine evaluation sets' 125 defects beyond 1 mm were proven inside it)
    disparity_noise_px: float = Field(0.25, ge=0.25)
    # surface: fit the surfaces to the images themselves (sub-pixel, with an uncertainty from the fit);
    # disparity: from the stereo backend's map alone (the reference, docs/benchmarks.md compares them)
    method: Literal["surface", "disparity"] = "surface"
    # The standard uncertainty of a deviation, in disparity pixels, that ``inspect validate`` plans with
    # when it checks that the working distance can resolve each rule's limit (docs/benchmarks.md).
    planning_sigma_px: float = Field(0.04, gt=0.0, le=2.0)


class Rule(Section):
    """Reject a defect of ``class`` (or any class) when ``quantity op threshold``."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True, allow_inf_nan=False)

    class_: str = Field("any", alias="class", min_length=1)
    quantity: Literal["deviation_mm", "distance_mm", "confidence", "area_mm2"]
    op: Literal[">", ">=", "<", "<="]
    threshold: float
    name: str | None = None

    def describe(self) -> str:
        return self.name or f"{self.class_} {self.quantity} {self.op} {self.threshold:g}"


class DecisionSection(Section):
    rules: list[Rule] = Field(default_factory=list)
    # A defect the detector finds but no rule covers: pass it (the default) or reject it.
    reject_unruled_defects: bool = False
    # ISO 14253-1: a rule rejects when the measurement is beyond its limit by more than the guard band
    # (coverage_factor x the measurement's standard uncertainty) and passes when it is inside by more;
    # in between, conformance is proven neither way and the part is rejected, passed or flagged for a
    # manual check as ``uncertain`` says.
    uncertain: Literal["reject", "pass", "flag"] = "reject"
    coverage_factor: float = Field(2.0, ge=0.0, le=5.0)


class ResultsSection(Section):
    path: str = "results"
    save_images: Literal["rejected", "all", "none"] = "rejected"
    # below this much free space on the results disk no more images are saved (one alarm): the decisions
    # that the store still has to write matter more
    min_free_mb: float = Field(200.0, ge=0)


class VerifySection(Section):
    """Parts whose verdicts are known, inspected before the line's first part (``core.verification``)."""

    # a labelled sequence (left/, right/, calib.yaml, labels/*.json, as ``inspect sim generate`` writes and
    # ``inspect eval depth`` reads): a recording of the plant's own master parts, each defect's true depth in its
    # labels. A part whose labels put a defect clearly beyond a limit must come out rejected, or the run does not
    # start. null: no check.
    path: str | None = Field(None, min_length=1)


class ViewSection(Section):
    """The operator's web page (``inspect run --view``)."""

    enabled: bool = False
    # Loopback by default: the page has no user accounts. Any other address warns, or asks for ``token``.
    host: str = Field("127.0.0.1", min_length=1)
    port: int = Field(8080, ge=1, le=65535)
    token: str | None = Field(None, min_length=8)
    jpeg_quality: int = Field(80, ge=30, le=100)
    # the page asks for at most this many live frames per second; below 0.1 the browser's wait between two
    # overflowed its timer (1e-300: 1e303 ms), and it asked as fast as it could
    max_fps: float = Field(10.0, ge=0.1, le=60.0)


# Threads per stage: more than any CPU this runs on has cores (torch's own bound is a C int)
MAX_THREADS = 256


class Recipe(Section):
    name: str = Field(min_length=1)
    description: str = ""
    # CPU threads of this process's torch and OpenCV stages; auto = half the cores, so that two stations
    # on one PC do not spin against each other (docs/benchmarks.md). ``inspect run --threads`` wins.
    threads: int | str = "auto"
    # A part still in inspection after this long means a stage or plugin is not returning: an alarm, and the
    # outputs tell the line the inspection is not ready (ready coil off, heartbeat stopped) until it finishes.
    # at most 10 minutes: a larger one only turned the watch off (and 1e300 s killed its thread)
    watchdog_s: float = Field(5.0, gt=0, le=600)
    camera: CameraSection
    stereo: StereoSection
    detector: DetectorSection = Field(default_factory=DetectorSection)
    depth: DepthSection = Field(default_factory=DepthSection)
    decision: DecisionSection = Field(default_factory=DecisionSection)
    outputs: list[PluginRef] = Field(default_factory=lambda: [PluginRef(plugin="log")])
    results: ResultsSection = Field(default_factory=ResultsSection)
    verify: VerifySection = Field(default_factory=VerifySection)
    view: ViewSection = Field(default_factory=ViewSection)

    @field_validator("threads", mode="before")
    @classmethod
    def _threads(cls, value):
        if value == "auto" or (isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= MAX_THREADS):
            return value
        raise ValueError(f"give auto or a number of threads, 1 to {MAX_THREADS}")
