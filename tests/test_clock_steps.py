"""``core.clock_steps``: the system clock set while a frame is inspected, on an injectable clock, and a run whose
clock is set during a frame's inspection."""
from __future__ import annotations

import sqlite3
import time

import pytest
from conftest import write_recipe
from test_engine import RECIPE

from core import engine
from core.clock_steps import STEP_TOLERANCE_S, ClockSteps
from core.contracts import PluginSpec
from core.hookspecs import hookimpl
from core.recipe import load_recipe
from core.registry import Registry, make_manager
from core.types import Detection


class Clocks:
    """A wall clock that can be set and a monotonic one that only runs."""

    def __init__(self):
        self.mono, self.offset = 100.0, 1.7e9

    def run(self, seconds: float) -> None:
        self.mono += seconds

    def wall(self) -> float:
        return self.mono + self.offset

    def monotonic(self) -> float:
        return self.mono


class TestClockSteps:
    def test_a_step_after_arrival_is_measured_and_time_passing_is_not(self):
        c = Clocks()
        steps = ClockSteps(c.wall, c.monotonic)
        steps.arrived("R1-000001")
        c.run(0.4)
        assert steps.since("R1-000001") == 0.0
        c.offset -= 0.5  # set back half a second: the reject would fire 0.5 s late, at the next plate
        c.run(0.1)
        assert steps.since("R1-000001") == pytest.approx(-0.5)
        steps.arrived("R1-000002")  # arrived on the new clock
        assert steps.since("R1-000002") == 0.0

    def test_slewing_within_the_tolerance_is_not_a_step(self):
        c = Clocks()
        steps = ClockSteps(c.wall, c.monotonic)
        steps.arrived("k")
        c.offset += STEP_TOLERANCE_S / 2
        assert steps.since("k") == 0.0

    def test_an_unknown_or_forgotten_key_has_no_step(self):
        c = Clocks()
        steps = ClockSteps(c.wall, c.monotonic)
        steps.arrived("k")
        c.offset += 3.0
        steps.forget("k")
        assert steps.since("k") == 0.0 and steps.since("never") == 0.0

    def test_the_clock_at_arrival_leaves_the_step_out(self):
        c = Clocks()
        steps = ClockSteps(c.wall, c.monotonic)
        steps.arrived("k")
        before = c.wall()
        c.run(0.2)
        c.offset += 30.0
        assert steps.clock_at_arrival("k")() == pytest.approx(before + 0.2)


class StepsTheClock:
    """A detector that finds the region given; while it looks at the first frame (its first call) the system
    clock is set."""

    class_names = ["pit"]

    def __init__(self, box, clock, step_s):
        self.box, self.clock, self.step_s, self.calls = box, clock, step_s, 0

    def detect(self, image):
        self.calls += 1
        if self.calls == 1:
            self.clock.offset += self.step_s
        return [Detection("pit", 0.9, self.box)]


class Witness:
    sent: list = []

    def submit(self, part):
        Witness.sent.append((part.part_id, part.timestamp))

    def poll(self):
        return []

    def close(self, timeout_s=10.0):
        return []


class SetClock:
    """The wall clock ``time.time`` reads, which the test sets."""

    def __init__(self):
        self.offset, self.real = 0.0, time.time

    def __call__(self) -> float:
        return self.real() + self.offset


@pytest.mark.parametrize("step_s", [-0.5, 30.0])
@pytest.mark.parametrize("concurrent", [False, True])
def test_a_clock_set_during_inspection_leaves_the_reject_timed_from_the_capture(
        tmp_path, plane_sequence, monkeypatch, step_s, concurrent):
    # the part's capture time went to the outputs as stamped, on the clock before the step: set back by half a
    # second its reject fired 0.5 s late, at the next plate, counted on time; set forward its frame was too old
    clock = SetClock()
    monkeypatch.setattr(time, "time", clock)
    info = plane_sequence([0.0, 0.0, 0.0])

    class Plugins:
        @hookimpl
        def stereo_inspect_detectors(self):
            return [PluginSpec("stepper", "detector", lambda s, ctx: StepsTheClock(tuple(info["box"]), clock, step_s),
                               class_names=lambda s, ctx: ["pit"])]

        @hookimpl
        def stereo_inspect_outputs(self):
            return [PluginSpec("witness", "output", lambda s, ctx: Witness(), actuator_delay=lambda s, ctx: 2.0)]

    registry = Registry(make_manager((Plugins(),)))
    text = RECIPE.format(box=info["box"], output="witness").replace("plugin: fixed_roi", "plugin: stepper")
    text = text.replace("  settings:\n    regions:\n      - {name: pit, box: " + str(info["box"]) + "}\n", "")
    text = text.replace("schedule: every_frame", f"schedule: every_frame\n  concurrent: {str(concurrent).lower()}")
    Witness.sent = []
    summary = engine.run(load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry), registry=registry,
                         device="cpu")
    assert summary.counts[engine.Status.ERROR] == 0  # a frame 30 s "old" on the new clock is not late
    stored = dict(sqlite3.connect(tmp_path / "results" / "results.db").execute("SELECT part_id, time FROM parts"))
    sent = dict(Witness.sent)
    # the frame whose inspection the step fell in: its capture on the clock as it now stands
    stepped = "R1-000000"
    assert sent[stepped] - stored[stepped] == pytest.approx(step_s, abs=STEP_TOLERANCE_S)
    for part_id in set(stored) - {stepped}:
        assert sent[part_id] == pytest.approx(stored[part_id], abs=1e-6), part_id
