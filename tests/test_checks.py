"""``core.checks``: what the engine checks of what plugins hand it, and the part a breach costs."""
from __future__ import annotations

import math
import shutil
import sqlite3

import numpy as np
import pytest
import stereo_inspect_fixed_roi
from conftest import write_recipe
from test_engine import RECIPE

from core import engine
from core.checks import (RepeatedImages, delivery_problem, detections_problem, disparity_problem, event_problem,
                         frame_problem)
from core.contracts import PluginSpec
from core.hookspecs import hookimpl
from core.recipe import RecipeError, load_recipe
from core.registry import Registry, make_manager
from core.types import Alarm, Calibration, Detection, FrameError, OutputEvent, Status, StereoFrame

CALIB = Calibration(focal_px=350.0, baseline_mm=120.0, cx=80.0, cy=60.0, width=160, height=120)


def _frame(left=None, right=None, calib=CALIB):
    image = np.zeros((120, 160, 3), np.uint8)
    return StereoFrame("000001", 1, image if left is None else left, image if right is None else right, calib, 0.0)


class TestFrameProblem:
    def test_a_pair_as_the_contract_has_it_passes(self):
        assert frame_problem(_frame()) is None

    @pytest.mark.parametrize("left, right, says", [
        (np.zeros((120, 160), np.uint8), None, "left image is uint8 of shape (120, 160), not HxWx3 uint8 BGR"),
        (None, np.zeros((120, 160, 3), np.float32), "right image is float32"),
        (None, np.zeros((120, 150, 3), np.uint8), "left and right images differ in size (160x120, 150x120)"),
        (np.zeros((60, 80, 3), np.uint8), np.zeros((60, 80, 3), np.uint8), "images are 80x60 but its calibration is for 160x120"),
        ([[0]], None, "left image is a list, not an array"),
    ])
    def test_a_broken_pair_is_named(self, left, right, says):
        assert says in frame_problem(_frame(left, right))

    @pytest.mark.parametrize("key, value", [("focal_px", -350.0), ("baseline_mm", 0.0), ("focal_px", math.nan)])
    def test_a_calibration_no_camera_has_is_named(self, key, value):
        calib = Calibration(**{**CALIB.__dict__, key: value})
        assert f"calibration has {key} {value!r}: not a positive number" in frame_problem(_frame(calib=calib))

    @pytest.mark.parametrize("key, value, says", [
        ("cx", 1e30, "cx 1e+30 lies far outside the 160 px wide image"),
        ("baseline_mm", 0.12, "baseline_mm 0.12 lies outside 1-10000 mm (metres written for millimetres?)"),
    ])
    def test_a_geometry_no_camera_has_is_named(self, key, value, says):
        calib = Calibration(**{**CALIB.__dict__, key: value})
        assert frame_problem(_frame(calib=calib)).startswith(f"the camera's calibration is no camera's: {says}")


class TestRepeatedImages:
    def frames(self, *seeds):
        rng = {s: np.random.default_rng(s) for s in set(seeds)}
        images = {s: (rng[s].integers(0, 255, (120, 160, 3), dtype=np.uint8),
                      rng[s].integers(0, 255, (120, 160, 3), dtype=np.uint8)) for s in set(seeds)}
        return [StereoFrame(f"{i:06d}", i, *images[s], CALIB, float(i)) for i, s in enumerate(seeds)]

    def test_new_images_pass_and_a_repeat_names_the_frame_it_repeats(self):
        repeats = RepeatedImages()
        said = [repeats.problem(f) for f in self.frames(0, 1, 1, 1, 2)]
        assert said[:2] == [None, None] and said[4] is None
        assert "frame 000001's images again" in said[2] and "frame 000001's" in said[3]

    def test_run_counts_the_repeats_in_a_row(self):
        repeats = RepeatedImages()
        runs = []
        for f in self.frames(0, 0, 0, 1, 1):
            repeats.problem(f)
            runs.append(repeats.run)
        assert runs == [0, 1, 2, 0, 1]

    def test_one_eye_changing_is_a_new_frame(self):
        a, b = self.frames(0, 1)
        repeats = RepeatedImages()
        repeats.problem(a)
        assert repeats.problem(StereoFrame("000001", 1, a.left, b.right, CALIB, 1.0)) is None

    def test_an_array_the_driver_refills_is_compared_by_its_contents(self):
        a, b = self.frames(0, 1)
        left, right = a.left.copy(), a.right.copy()
        repeats = RepeatedImages()
        assert repeats.problem(StereoFrame("000000", 0, left, right, CALIB, 0.0)) is None
        left[:], right[:] = b.left, b.right  # the same arrays, a new exposure in them
        assert repeats.problem(StereoFrame("000001", 1, left, right, CALIB, 1.0)) is None
        assert repeats.problem(StereoFrame("000002", 2, left, right, CALIB, 2.0)) is not None


class TestDetectionsProblem:
    def test_good_boxes_pass(self):
        assert detections_problem([Detection("pit", 0.9, (1, 2, 3.5, 4)), Detection("pit", 0.9, (np.float32(1), 2, 3, 4))]) is None
        assert detections_problem([]) is None

    @pytest.mark.parametrize("found, says", [
        ((Detection("pit", 0.9, (1, 2, 3, 4)),), "returned a tuple, not a list"),
        ([{"box": (1, 2, 3, 4)}], "returned a dict among its detections"),
        ([Detection("pit", 0.9, (1, 2, math.nan, 4))], "a pit box (1, 2, nan, 4)"),
        ([Detection("pit", 0.9, (5, 2, 3, 4))], "x0 < x1"),
        ([Detection("pit", 0.9, (1, 2, 3))], "not (x0, y0, x1, y1)"),
        ([Detection("pit", math.nan, (1, 2, 3, 4))], "a pit with confidence nan, not a number in [0, 1]"),
        ([Detection("pit", 1.5, (1, 2, 3, 4))], "confidence 1.5"),
        ([Detection("pit", "high", (1, 2, 3, 4))], "confidence 'high'"),
    ])
    def test_a_broken_box_is_named(self, found, says):
        assert says in detections_problem(found)

    def test_a_box_that_misses_the_image_is_named(self):
        # a defect where there is no image: nothing there can be measured, and the detector is wrong
        shape = (376, 672)
        inside = [Detection("pit", 0.9, (-5, -5, 10, 10)), Detection("pit", 0.9, (660, 370, 700, 400))]
        assert detections_problem(inside, shape=shape) is None
        for box in [(672, 2, 700, 4), (1, 376, 3, 380), (-9, 2, 0, 4), (1, -9, 3, 0)]:
            assert detections_problem(inside + [Detection("pit", 0.9, box)], shape=shape) == \
                f"the detector returned a pit box {tuple(float(v) for v in box)} outside the 672x376 image"
        assert detections_problem([Detection("pit", 0.9, (672, 2, 700, 4))]) is None  # no shape: not held to

    def test_a_class_the_detector_does_not_state_is_named(self):
        # a rule for one class would never cover it: the part would pass
        found = [Detection("pit", 0.9, (1, 2, 3, 4)), Detection("rust", 0.9, (1, 2, 3, 4))]
        assert detections_problem(found[:1], ["pit", "scratch"]) is None
        assert detections_problem(found, ["pit", "scratch"]) == \
            "the detector returned a 'rust', not one of the classes it states (pit, scratch)"
        assert detections_problem(found) is None and detections_problem(found, []) is None  # none stated: none held to


class TestDisparityProblem:
    def test_a_map_of_the_images_shape_passes(self):
        assert disparity_problem(np.zeros((120, 160), np.float32), (120, 160)) is None
        assert disparity_problem(np.zeros((120, 160), np.int16), (120, 160)) is None

    @pytest.mark.parametrize("disparity, says", [
        (np.zeros((60, 80), np.float32), "a map of shape (60, 80) for a 160x120 image"),
        (np.zeros((120, 160, 1), np.float32), "shape (120, 160, 1)"),
        (np.zeros((120, 160), bool), "a map of bool, not numbers"),
        ([[0.0]], "returned a list, not an array"),
    ])
    def test_a_broken_map_is_named(self, disparity, says):
        assert says in disparity_problem(disparity, (120, 160))

    def test_matches_lie_in_the_searched_range_or_a_pixel_beyond(self):
        disparity = np.full((120, 160), 20.0, np.float32)
        disparity[:, :80] = np.nan  # unmatched
        disparity[:, 80:90] = 0.0  # "no match" for many matchers
        disparity[0, 100] = 41.0  # one overshoot among thousands: a refinement's, not the map's scale
        disparity[1, 100:105] = 9.2
        assert disparity_problem(disparity, (120, 160), (10.0, 40.0)) is None

    @pytest.mark.parametrize("scale, says", [
        (16.0, "disparities of 320 to 320 px, 100% of them outside the 10 to 40 px it was asked to search"),
        (0.25, "disparities of 5 to 5 px"),  # a map of a quarter-size pair not scaled back
    ])
    def test_a_map_in_other_units_is_named(self, scale, says):
        disparity = np.full((120, 160), 20.0 * scale, np.float32)
        assert says in disparity_problem(disparity, (120, 160), (10.0, 40.0))
        assert disparity_problem(disparity, (120, 160)) is None  # no range given: none checked

    def test_zero_and_below_are_no_match_not_a_value_outside(self):
        disparity = np.full((120, 160), 20.0, np.float32)
        disparity[:60] = -1.0  # a matcher's "no match", as OpenCV's min_disp - 1
        disparity[60:80] = 0.0
        assert disparity_problem(disparity, (120, 160), (10.0, 40.0)) is None


class TestDeliveryProblem:
    def test_frames_and_frame_errors_with_an_id_and_an_index_pass(self):
        assert delivery_problem(_frame()) is None
        assert delivery_problem(FrameError("000007", np.int64(7), "USB reset", 1e9)) is None

    @pytest.mark.parametrize("item, says", [
        (None, "the camera delivered a NoneType (None), not a StereoFrame or a FrameError"),
        ((np.zeros((2, 2, 3)),), "the camera delivered a tuple ((array([[["),  # on one line, however numpy prints
        (FrameError(None, 3, "lost", 1e9), "a frame whose frame_id is None, not text"),
        (FrameError("000003", "3", "lost", 1e9), "frame 000003 with index '3', not a whole number of 0 or more"),
        (FrameError("000003", -1, "lost", 1e9), "with index -1, not a whole number"),
        (FrameError("000003", True, "lost", 1e9), "with index True, not a whole number"),
    ])
    def test_what_no_part_can_be_named_from_is_said(self, item, says):
        assert says in delivery_problem(item)


class TestEventProblem:
    def test_events_and_alarms_the_store_can_hold_pass(self):
        assert event_problem(OutputEvent("plc", "R1-000001", "coil 0", "delivered", 1e9)) is None
        assert event_problem(OutputEvent("plc", None, "ready", "failed", 0, "timeout")) is None
        assert event_problem(Alarm("plc", "PLC unreachable", 1e9, "R1-000001", "link")) is None

    @pytest.mark.parametrize("event, says", [
        ("delivered", "a str ('delivered'), not an OutputEvent or an Alarm"),
        (None, "a NoneType (None), not an OutputEvent or an Alarm"),
        (OutputEvent("plc", "R1", {"coil": 0}, "delivered", 1.0), "whose command the store cannot hold"),
        (OutputEvent("plc", 7, "coil 0", "delivered", 1.0), "whose part_id the store cannot hold"),
        (OutputEvent("plc", "R1", "coil 0", "delivered", np.float32(1.0)), "whose timestamp the store cannot hold"),
        (Alarm("plc", "down", math.nan), "whose timestamp the store cannot hold"),
        (Alarm("plc", None, True), "whose message, timestamp the store cannot hold"),
    ])
    def test_what_the_store_cannot_hold_is_named(self, event, says):
        assert says in event_problem(event)


# -- the part a breach costs: an ERROR naming it, the run going on ------------------------------------------

class HalfMap:
    """A backend that forgot to scale its map back to the image."""

    def compute(self, left, right, min_disp, max_disp):
        return np.full((left.shape[0] // 2, left.shape[1] // 2), 90.0, np.float32)


class FixedPoint:
    """A backend that hands over its matcher's fixed-point map (disparity x 16) as it is."""

    def __init__(self, ctx):
        from core.registry import default_registry

        self.sgbm = default_registry().get("stereo", "opencv_sgbm").spec.factory({}, ctx)

    def compute(self, left, right, min_disp, max_disp):
        return self.sgbm.compute(left, right, min_disp, max_disp) * 16.0


class Scribbler(FixedPoint):
    """A backend that works on the images it is given in place (an exposure correction, say)."""

    def compute(self, left, right, min_disp, max_disp):
        disparity = self.sgbm.compute(left, right, min_disp, max_disp)
        left[:] = 0
        right[:] = 0
        return disparity


class NanBoxes:
    class_names = ["pit"]

    def detect(self, image):
        return [Detection("pit", 0.9, (10.0, 10.0, math.nan, 40.0))]


class DrawsOnInput:
    """A detector that marks what it found on the image it was given, which stereo and depth then measure."""

    class_names = ["pit"]

    def detect(self, image):
        image[10:40, 10:40] = 255
        return [Detection("pit", 0.9, (10.0, 10.0, 40.0, 40.0))]


class NarrowRight:
    """A camera whose right image comes cropped: the replay's frames with 10 columns cut off."""

    def __init__(self, settings, ctx):
        from plugins.replay_camera import ReplayCamera, ReplaySettings

        self.replay = ReplayCamera(ReplaySettings(path=str(ctx.recipe_dir / "seq")))

    def frames(self):
        for frame in self.replay.frames():
            frame.right = frame.right[:, 10:]
            yield frame

    def close(self):
        self.replay.close()


class YieldsNone(NarrowRight):
    """A camera whose grab returned nothing for its second frame, and which handed that on."""

    def frames(self):
        for frame in self.replay.frames():
            yield None if frame.index == 1 else frame


class FarCentre(NarrowRight):
    """A camera whose calibration puts the principal point far outside the image: every deviation would be
    about 0 mm, every plate passed."""

    def frames(self):
        for frame in self.replay.frames():
            frame.calib = Calibration(**{**frame.calib.__dict__, "cx": 1e30})
            yield frame


def _far_centre_calibration(settings, ctx):
    return Calibration(focal_px=350.0, baseline_mm=120.0, cx=1e30, cy=96.0, width=320, height=192)


class Plugins:
    @hookimpl
    def stereo_inspect_cameras(self):
        return [PluginSpec("narrow_right", "camera", NarrowRight), PluginSpec("far_centre", "camera", FarCentre),
                PluginSpec("yields_none", "camera", YieldsNone),
                PluginSpec("far_centre_stated", "camera", FarCentre, calibration=_far_centre_calibration)]

    @hookimpl
    def stereo_inspect_stereo_backends(self):
        return [PluginSpec("half_map", "stereo", lambda s, ctx: HalfMap()),
                PluginSpec("fixed_point", "stereo", lambda s, ctx: FixedPoint(ctx)),
                PluginSpec("scribbler", "stereo", lambda s, ctx: Scribbler(ctx))]

    @hookimpl
    def stereo_inspect_detectors(self):
        return [PluginSpec("nan_boxes", "detector", lambda s, ctx: NanBoxes(), class_names=lambda s, ctx: ["pit"]),
                PluginSpec("draws_on_input", "detector", lambda s, ctx: DrawsOnInput(),
                           class_names=lambda s, ctx: ["pit"])]


@pytest.mark.parametrize("old, new, says", [
    ("backend: opencv_sgbm", "backend: half_map", "stereo failed: the stereo backend returned a map of shape"),
    ("backend: opencv_sgbm", "backend: fixed_point", "stereo failed: the stereo backend returned disparities of"),
    ("plugin: fixed_roi", "plugin: nan_boxes", "detection failed: the detector returned a pit box (10.0, 10.0, nan, 40.0)"),
    ("plugin: fixed_roi", "plugin: draws_on_input", "detection failed: ValueError: assignment destination is read-only"),
    ("plugin: replay\n  settings: {path: seq}", "plugin: narrow_right",
     "the camera's left and right images differ in size (320x192, 310x192)"),
    ("plugin: replay\n  settings: {path: seq}", "plugin: far_centre",
     "the camera's calibration is no camera's: cx 1e+30 lies far outside the 320 px wide image"),
])
def test_a_plugin_that_breaks_its_contract_costs_its_part_an_error(tmp_path, plane_sequence, old, new, says):
    info = plane_sequence([0.0, 0.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, Plugins())))
    text = RECIPE.format(box=info["box"], output="log").replace(old, new)
    if new in ("plugin: nan_boxes", "plugin: draws_on_input"):
        text = text.replace("  settings:\n    regions:\n      - {name: pit, box: " + str(info["box"]) + "}\n", "")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR, Status.ERROR]
    assert all(says in o.part.verdict.reasons[0] for o in seen), seen[0].part.verdict.reasons
    assert summary.exit_code == engine.EXIT_PART_ERRORS


@pytest.mark.parametrize("concurrent", [False, True])
def test_a_camera_that_yields_none_stops_the_run_with_an_alarm_not_as_its_end(tmp_path, plane_sequence, concurrent):
    # the None was taken for the end of the camera's frames: exit 0, and the plates after it never inspected
    info = plane_sequence([0.0, 0.0, 2.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, Plugins())))
    text = RECIPE.format(box=info["box"], output="log").replace("plugin: replay\n  settings: {path: seq}",
                                                                "plugin: yields_none")
    text = text.replace("schedule: every_frame", f"schedule: every_frame\n  concurrent: {str(concurrent).lower()}")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry)
    summary = engine.run(loaded, registry=registry, device="cpu")
    (alarm,) = summary.alarms
    assert alarm.message == ("run stopped after 1 parts: CameraFailed: the camera delivered a NoneType (None), not a "
                             "StereoFrame or a FrameError")
    assert summary.exit_code == engine.EXIT_ALARMS


def test_a_camera_stating_a_geometry_no_camera_has_is_refused_before_the_run(tmp_path, plane_sequence):
    info = plane_sequence([0.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, Plugins())))
    text = RECIPE.format(box=info["box"], output="log").replace("plugin: replay\n  settings: {path: seq}",
                                                                "plugin: far_centre_stated")
    with pytest.raises(RecipeError, match=r"camera: the camera's calibration is no camera's: cx 1e\+30 lies far outside"):
        load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry)


def test_a_backend_that_works_on_its_images_in_place_leaves_the_frame_the_surface_fit_reads(tmp_path, plane_sequence):
    # from column 0 (min_disparity 0, full scale) the backend was handed the frame's own images, and the
    # surface fit then measured what the backend had left of them
    info = plane_sequence([0.0, 2.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, Plugins())))
    measured = {}
    for backend in ("opencv_sgbm", "scribbler"):
        text = RECIPE.format(box=info["box"], output="log").replace(
            "backend: opencv_sgbm", f"backend: {backend}").replace(
            "working_distance_mm: [300, 600]", "min_disparity: 0\n  max_disparity: 160")
        folder = tmp_path / backend
        folder.mkdir()
        shutil.copytree(info["folder"], folder / "seq")
        loaded = load_recipe(write_recipe(folder / "r.yaml", text), registry=registry)
        seen = []
        engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
        measured[backend] = [(o.part.verdict.status, [m.deviation_mm for m in o.part.measurements]) for o in seen]
    assert measured["scribbler"] == measured["opencv_sgbm"]
    assert [status for status, _ in measured["opencv_sgbm"]] == [Status.PASS, Status.REJECT]


class Pardoner:
    """An output that marks every part it is handed as passed (a reject counter resetting the part, say)."""

    def submit(self, part):
        part.verdict.status = Status.PASS

    def poll(self):
        return []

    def close(self, timeout_s=10.0):
        return []


class Witness(Pardoner):
    seen: list = []

    def submit(self, part):
        Witness.seen.append((part.part_id, part.verdict.status))


class Outputs:
    @hookimpl
    def stereo_inspect_outputs(self):
        delay = {"actuator_delay": lambda s, ctx: 2.0}
        return [PluginSpec("pardoner", "output", lambda s, ctx: Pardoner(), **delay),
                PluginSpec("witness", "output", lambda s, ctx: Witness(), **delay)]


def test_an_output_that_changes_the_part_changes_it_for_itself_alone(tmp_path, plane_sequence):
    # the outputs shared the decided part: a verdict one of them changed reached the outputs after it
    info = plane_sequence([0.0, 2.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, Outputs())))
    text = RECIPE.format(box=info["box"], output="pardoner\n  - plugin: witness")
    Witness.seen = []
    seen = []
    engine.run(load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry), registry=registry,
               on_part=seen.append, device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.PASS, Status.REJECT]
    assert [status for _, status in Witness.seen] == [Status.PASS, Status.REJECT]


class Misreporter(Pardoner):
    """An output that sends its commands but reports them wrongly: its ``poll`` fails once, then says
    "delivered" as a string; its ``close`` returns nothing."""

    def __init__(self):
        self.polls = 0

    def submit(self, part):
        pass

    def poll(self):
        self.polls += 1
        if self.polls == 1:
            raise ConnectionResetError("status register unreadable")
        return ["delivered"]

    def close(self, timeout_s=10.0):
        return None


class Misreporting:
    @hookimpl
    def stereo_inspect_outputs(self):
        delay = {"actuator_delay": lambda s, ctx: 2.0}
        return [PluginSpec("misreporter", "output", lambda s, ctx: Misreporter(), **delay),
                PluginSpec("witness", "output", lambda s, ctx: Witness(), **delay)]


def test_an_output_that_misreports_raises_alarms_and_the_line_goes_on(tmp_path, plane_sequence):
    # a poll that raised stopped the run after its first part, leaving the next outputs without it; a report
    # the store could not write made the engine take the store for broken and stop the line
    info = plane_sequence([0.0, 2.0, 0.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, Misreporting())))
    text = RECIPE.format(box=info["box"], output="misreporter\n  - plugin: witness")
    Witness.seen = []
    summary = engine.run(load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry),
                         registry=registry, device="cpu")
    assert summary.frames == 3 and summary.counts[Status.REJECT] == 1
    assert [part_id for part_id, _ in Witness.seen] == ["R1-000000", "R1-000001", "R1-000002"]
    says = [a.message for a in summary.alarms]
    assert says[0].startswith("asking the output what it sent failed after R1-000000: ConnectionResetError")
    assert says[1:3] == ["the output reported a str ('delivered'), not an OutputEvent or an Alarm: left out, what "
                         "it meant is lost"] * 2
    assert says[3].startswith("the output reported a NoneType, not a list")
    assert all(a.source == "misreporter" for a in summary.alarms) and summary.exit_code == engine.EXIT_ALARMS
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    assert db.execute("SELECT COUNT(*) FROM alarms").fetchone()[0] == 4  # the store kept working
    assert db.execute("SELECT exit_code FROM runs").fetchone()[0] == engine.EXIT_ALARMS
