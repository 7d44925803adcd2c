"""Frames a free-running camera captured while the loop was busy: each is its plate's ERROR, never a silent pass."""
from __future__ import annotations

import dataclasses
import math
import sqlite3
import time

import pytest
import stereo_inspect_fixed_roi
from conftest import write_recipe
from test_engine import RECIPE

from core import engine
from core.contracts import PluginSpec
from core.hookspecs import hookimpl
from core.recipe import load_recipe
from core.registry import Registry, make_manager
from core.types import FrameError, Status
from core.unread_frames import UnreadFrame, UnreadFrames
from plugins.replay_camera import ReplayCamera, ReplaySettings


def _frame(index: int, stamp: float) -> FrameError:
    return FrameError(f"{index:06d}", index, "stands in for a frame: only its stamp is read", stamp)


class Clocks:
    """The wall clock and the monotonic one of a loop that receives each frame 30 ms after its capture."""

    def __init__(self, rate=10.0):
        self.wall = self.mono = 0.0
        self.unread = UnreadFrames(rate, clock=lambda: self.wall, monotonic=lambda: self.mono)

    def between(self, frame, step_s=0.0):
        """``frame`` reaches the loop; ``step_s``: the wall clock was set forward by that much before."""
        elapsed = frame.timestamp + 0.03 - step_s - self.wall if self.wall else 0.0
        self.wall, self.mono = frame.timestamp + 0.03, self.mono + elapsed
        return self.unread.between(frame)


class TestUnreadFrames:
    def test_frames_a_period_apart_leave_nothing_unread(self):
        unread = UnreadFrames(10.0)
        # a capture clock's jitter up to 0.4 of a period is not a frame gone by
        stamps = [100.0, 100.1, 100.24, 100.3, 100.4]
        assert [unread.between(_frame(i, t)) for i, t in enumerate(stamps)] == [[]] * 5
        assert unread.alarm() is None

    def test_each_period_without_a_frame_is_one_unread_frame_stamped_with_its_period(self):
        unread = UnreadFrames(10.0)
        unread.between(_frame(4, 100.0))
        missed = unread.between(dataclasses.replace(_frame(5, 100.3), source="cam"))
        assert [m.frame_id for m in missed] == ["000004+1", "000004+2"]
        assert [(m.index, m.slot, m.source) for m in missed] == [(4, 1, "cam"), (4, 2, "cam")]
        assert [m.timestamp for m in missed] == pytest.approx([100.1, 100.2])
        assert all(isinstance(m, UnreadFrame) and isinstance(m, FrameError) for m in missed)
        assert missed[0].message.startswith("frame period 1 of 2 after frame 000004: no frame was read (the camera "
                                            "runs at 10 frames a second), so its part went by uninspected")

    def test_a_camera_that_states_no_rate_is_never_checked(self):
        for rate in (None, 0.0):
            unread = UnreadFrames(rate)
            assert unread.between(_frame(0, 100.0)) == [] and unread.between(_frame(1, 160.0)) == []

    @pytest.mark.parametrize("bad", [math.nan, math.inf, None, "noon"])
    def test_a_stamp_that_is_not_a_time_restarts_the_count(self, bad):
        unread = UnreadFrames(10.0)
        unread.between(_frame(0, 100.0))
        assert unread.between(_frame(1, bad)) == []
        assert unread.between(_frame(2, 100.5)) == []  # not counted from a stamp that is not a time
        assert len(unread.between(_frame(3, 100.8))) == 2

    def test_a_clock_set_forward_is_no_gap(self):
        clocks = Clocks()
        clocks.between(_frame(0, 100.0))
        # the next frame, a period later, stamped after the clock was set an hour forward
        assert clocks.between(_frame(1, 3700.1), step_s=3600.0) == []
        assert len(clocks.between(_frame(2, 3700.4))) == 2  # and frames missed after it still count

    def test_a_clock_set_back_during_a_stall_still_counts_its_frames_on_the_new_clock(self):
        clocks = Clocks()
        clocks.between(_frame(0, 100.0))
        # half a second without a frame read, during which the clock was set back by a second: the next stamp
        # lies before the last one, which had read as no gap at all
        missed = clocks.between(_frame(1, 99.5), step_s=-1.0)
        assert [m.frame_id for m in missed] == ["000000+1", "000000+2", "000000+3", "000000+4"]
        # stamped on the clock as it now stands, so that each reject fires at its plate
        assert [m.timestamp for m in missed] == pytest.approx([99.1, 99.2, 99.3, 99.4])

    def test_frames_missed_across_a_clock_set_forward_are_stamped_on_the_new_clock(self):
        clocks = Clocks()
        clocks.between(_frame(0, 100.0))
        missed = clocks.between(_frame(1, 3700.3), step_s=3600.0)
        assert [m.timestamp for m in missed] == pytest.approx([3700.1, 3700.2])

    def test_a_stall_on_both_clocks_is_every_period_of_it(self):
        clocks = Clocks()
        clocks.between(_frame(0, 100.0))
        assert len(clocks.between(_frame(1, 105.0))) == 49

    def test_a_stamp_that_goes_back_is_no_gap(self):
        unread = UnreadFrames(10.0)
        unread.between(_frame(0, 100.0))
        assert unread.between(_frame(1, 99.0)) == []
        assert unread.between(_frame(2, 99.1)) == []

    def test_one_alarm_per_spell_and_a_second_read_in_time_ends_it(self):
        unread = UnreadFrames(4.0)
        t = [100.0]

        def read(periods):
            t[0] += periods / 4.0
            return unread.between(_frame(0, t[0]))

        read(0)
        assert unread.alarm() is None
        read(3)  # two frames missed
        alarm = unread.alarm("R1-000007")
        assert alarm.cause == "behind" and alarm.source == "camera" and alarm.part_id == "R1-000007"
        assert alarm.message.startswith("frames not read: 2 frame period(s) after frame 000000 without a frame read")
        assert unread.alarm() is None  # taken
        for periods in (1, 1, 1, 2, 1, 3):  # gaps in the same spell: fewer than 4 frames (a second) read in time
            read(periods)
            assert unread.alarm() is None
        for _ in range(4):
            read(1)
        read(2)  # after a second read in time: a new spell
        assert "1 frame period(s)" in unread.alarm().message


class FreeRunningCamera:
    """The plane sequence as a camera running at ``RATE`` frames a second whose driver kept only the newest
    frame while the loop was busy: frames 0-1 read in time, then two periods lost, then three frames in time,
    then one lost. Its capture stamps lie on the camera's clock, a second back."""

    RATE = 10.0
    PERIODS = (0, 1, 4, 5, 6, 8)  # the period each frame read was captured in

    def __init__(self, folder):
        self.replay = ReplayCamera(ReplaySettings(path=str(folder)))

    def frames(self):
        start = time.time() - 1.0
        for period, frame in zip(self.PERIODS, self.replay.frames()):
            yield dataclasses.replace(frame, timestamp=start + period / self.RATE)

    def close(self):
        pass


class FreeRunningPlugin:
    def __init__(self, folder):
        self.folder = folder

    @hookimpl
    def stereo_inspect_cameras(self):
        return [PluginSpec("free", "camera", lambda s, ctx: FreeRunningCamera(self.folder),
                           frame_rate=lambda s, ctx: FreeRunningCamera.RATE)]


@pytest.mark.parametrize("concurrent", [True, False])
def test_frames_the_camera_captured_while_the_loop_was_busy_are_errors_rejected_and_alarmed(
        tmp_path, plane_sequence, concurrent):
    info = plane_sequence([0.0, 0.1, 0.2, 0.3, 0.4, 0.5])  # pits too shallow to reject; six images, none repeated
    registry = Registry(make_manager((stereo_inspect_fixed_roi, FreeRunningPlugin(info["folder"]))))
    text = RECIPE.format(box=info["box"], output="log").replace("plugin: replay\n  settings: {path: seq}",
                                                                "plugin: free")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), [f"stereo.concurrent={concurrent}"],
                         registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")

    assert [o.part.part_id for o in seen] == ["R1-000000", "R1-000001", "R1-000001+1", "R1-000001+2", "R1-000002",
                                              "R1-000003", "R1-000004", "R1-000004+1", "R1-000005"]
    unseen = [o.part for o in seen if "+" in o.part.part_id]
    assert all(p.verdict.status is Status.ERROR for p in unseen)
    assert [p.timestamp - seen[0].part.timestamp for p in unseen] == pytest.approx([0.2, 0.3, 0.7])
    assert all(o.part.verdict.status is Status.PASS for o in seen if "+" not in o.part.part_id)
    # one alarm: the second gap lies within a second of the first
    assert [(a.source, a.cause) for a in summary.alarms] == [("camera", "behind")]
    assert summary.exit_code == engine.EXIT_ALARMS
    from core.commands.inspection import alarm_hints
    hints = alarm_hints(summary.alarms, loaded, plc_sim_given=False)
    assert any("frames the camera captured were not read" in h for h in hints)
    assert not any("stopped delivering" in h for h in hints)  # the camera did deliver

    db = sqlite3.connect(tmp_path / "results" / "results.db")
    stored = db.execute("SELECT part_id, verdict FROM parts WHERE part_id LIKE '%+%' ORDER BY id").fetchall()
    assert stored == [("R1-000001+1", "ERROR"), ("R1-000001+2", "ERROR"), ("R1-000004+1", "ERROR")]
    sent = db.execute("SELECT part_id, command FROM output_events WHERE part_id LIKE '%+%' ORDER BY id").fetchall()
    assert sent == [(p, f"REJECT {p} ERROR") for p, _ in stored]
