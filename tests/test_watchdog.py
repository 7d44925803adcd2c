"""``core.watchdog.StallWatch`` on an injected clock: ``check()`` called by the test, no thread; and its thread."""
from __future__ import annotations

import threading

import pytest

from core.watchdog import StallWatch


class Clock:
    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def _watch(limit_s=2.0):
    clock, calls = Clock(), []
    watch = StallWatch(limit_s, lambda key, what, s: calls.append(("stall", key, what, s)),
                       lambda s: calls.append(("resume", s)), clock)
    return watch, clock, calls


class TestStallWatch:
    def test_a_frame_finished_within_the_limit_raises_nothing(self):
        watch, clock, calls = _watch()
        watch.started("P1", "frame 000001")
        clock.now += 1.9
        watch.check()
        watch.finished("P1")
        clock.now += 10.0
        watch.check()
        assert calls == [] and not watch.stalled

    def test_a_frame_past_the_limit_stalls_once_and_resumes_once_when_it_finishes(self):
        watch, clock, calls = _watch()
        watch.started("P1", "frame 000001")
        clock.now += 2.5
        watch.check()
        clock.now += 5.0
        watch.check()
        assert calls == [("stall", "P1", "frame 000001", 2.5)] and watch.stalled
        watch.finished("P1")
        assert calls[1:] == [("resume", 7.5)] and not watch.stalled

    def test_the_oldest_frame_is_the_one_named(self):
        watch, clock, calls = _watch()
        watch.started("P1", "frame 000001")
        clock.now += 1.0
        watch.started("P2", "frame 000002")
        clock.now += 1.5
        watch.check()
        assert calls == [("stall", "P1", "frame 000001", 2.5)]

    def test_the_stall_lasts_while_any_frame_is_late(self):
        # the frame read ahead of a stuck one waits as long as it: it is late too
        watch, clock, calls = _watch()
        watch.started("P1", "frame 000001")
        watch.started("P2", "frame 000002")
        clock.now += 3.0
        watch.check()
        watch.finished("P1")
        assert watch.stalled and [c[0] for c in calls] == ["stall"]
        watch.finished("P2")
        assert [c[0] for c in calls] == ["stall", "resume"]

    def test_a_new_frame_after_the_stall_starts_its_own_time(self):
        watch, clock, calls = _watch()
        watch.started("P1", "frame 000001")
        clock.now += 3.0
        watch.check()
        watch.started("P2", "frame 000002")
        watch.finished("P1")
        assert [c[0] for c in calls] == ["stall", "resume"]
        clock.now += 2.5
        watch.check()
        assert [c[0] for c in calls] == ["stall", "resume", "stall"] and calls[-1][1] == "P2"

    def test_after_close_finishing_resumes_nothing(self):
        watch, clock, calls = _watch()
        watch.started("P1", "frame 000001")
        clock.now += 3.0
        watch.check()
        watch.close()
        watch.finished("P1")
        assert [c[0] for c in calls] == ["stall"]

    def test_a_frame_may_have_a_limit_of_its_own(self):
        watch, clock, calls = _watch()
        watch.started("camera", "the camera's first frame", 30.0)
        clock.now += 10.0
        watch.check()
        assert calls == []
        clock.now += 25.0
        watch.check()
        assert calls == [("stall", "camera", "the camera's first frame", 35.0)]

    def test_the_limit_must_be_positive(self):
        with pytest.raises(ValueError, match="limit_s"):
            StallWatch(0.0, lambda *a: None, lambda s: None)


def test_the_watch_s_thread_looks_at_least_once_a_second_whatever_its_limit():
    # limit_s / 4 = 2.5e299 s was no wait the thread could make (OverflowError): it died, and a frame with a
    # limit of its own was never watched
    stalled = threading.Event()
    watch = StallWatch(1e300, lambda key, what, s: stalled.set(), lambda s: None).start()
    try:
        watch.started("camera", "no frame from the camera", limit_s=0.05)
        assert stalled.wait(5.0)
    finally:
        watch.close()
