"""Frames a free-running camera captured that the loop never read.

A camera that runs at its own rate (a ZED at 15 frames a second) does not wait for the inspection: when
a frame takes longer than the camera's period, the driver keeps only the newest frame and the ones before
it are gone (a V4L2 queue of one, the ZED SDK's grab). Each frame is a part, so a frame nobody read is a
plate that went by uninspected, and nothing else in the loop would notice. The capture times say it:
consecutive frames more than one period apart had frames between them.

``UnreadFrames.between(item)`` gives one ``UnreadFrame`` (a ``FrameError``, so an ERROR part whose reject
is timed from when its plate passed the camera) for every period with no frame since the one before;
``alarm`` raises one alarm per spell of them. The replay camera stamps the schedule it plays, so a replay
never shows a gap; a camera that states no frame rate (one triggered by the parts) is never checked.

Capture stamps are wall-clock times, which setting the clock (NTP, an operator) moves by as much as it was
set. The step since the frame before reached the loop (``core.clock_steps``) is taken out of the gap, and the
unread frames are stamped on the clock as it now stands, so that their rejects fire at their plates: set back
by a second, a half-second stall had read as a stamp going back, its plates not counted at all. The gap counted
is also never more than the time that passed on the monotonic clock since the frame before reached the loop,
plus that frame's age then, so that a step between a frame's capture and its arrival, which cannot be told from
a late frame, cannot make an hour of frames either.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

from core.clock_steps import ClockSteps
from core.types import Alarm, FrameError, StereoFrame

_LAST = "the frame before"  # ClockSteps' key for the last frame that reached the loop


@dataclass
class UnreadFrame(FrameError):
    """The ``slot``-th frame period after the frame at ``index``, in which no frame was read."""

    slot: int = 1


class UnreadFrames:
    """rate_fps: the camera's frame rate (None or 0: nothing to check)."""

    def __init__(self, rate_fps: float | None, clock: Callable[[], float] = time.time,
                 monotonic: Callable[[], float] = time.monotonic):
        self.rate = float(rate_fps) if rate_fps else None
        self._clock, self._monotonic = clock, monotonic
        self._steps = ClockSteps(clock, monotonic)
        self._last: StereoFrame | FrameError | None = None
        self._last_reached: tuple[float, float] = (0.0, 0.0)  # (monotonic time, its age) when it reached the loop
        self._read_in_time = 0  # frames read in a row, each one period after the one before
        self._in_spell = False
        self._new_spell: list[UnreadFrame] = []  # the gap that began a spell, until its alarm is taken

    def between(self, item: StereoFrame | FrameError) -> list[UnreadFrame]:
        """The frame periods between the last item's capture and ``item``'s in which no frame was read, in
        order, each stamped with its period's capture time (the last one's plus k periods) on the clock as it
        now stands. A capture time that is not a number or goes back restarts the count from ``item``."""
        last, self._last = self._last, item
        step = self._steps.since(_LAST)  # the wall clock set since the last frame reached the loop
        self._steps.arrived(_LAST)
        (then, age), now = self._last_reached, self._monotonic()
        self._last_reached = (now, self._clock() - item.timestamp if _finite(item.timestamp) else 0.0)
        if self.rate is None or last is None or not (_finite(item.timestamp) and _finite(last.timestamp)):
            return []
        gap = min(item.timestamp - last.timestamp - step, now - then + max(age, 0.0))
        periods = math.floor(gap * self.rate + 0.5)
        unread = [UnreadFrame(f"{last.frame_id}+{k}", last.index,
                              f"frame period {k} of {periods - 1} after frame {last.frame_id}: no frame was read "
                              f"(the camera runs at {self.rate:g} frames a second), so its part went by uninspected",
                              last.timestamp + step + k / self.rate, item.source, k)
                  for k in range(1, periods)]
        if not unread:
            self._read_in_time += 1
            if self._read_in_time >= math.ceil(self.rate):  # a second of frames read in time ends a spell
                self._in_spell = False
        else:
            if not self._in_spell:
                self._new_spell = unread
            self._in_spell, self._read_in_time = True, 0
        return unread

    def alarm(self, part_id: str | None = None) -> Alarm | None:
        """The alarm for the gap that began a spell of unread frames, once; None otherwise. A spell ends when
        a second of the camera's frames has been read in time."""
        if not self._new_spell:
            return None
        first, self._new_spell = self._new_spell, []
        return Alarm("camera", f"frames not read: {len(first)} frame period(s) after frame "
                               f"{self._frame_before(first[0])} without a frame read (the camera runs at {self.rate:g} "
                               f"frames a second); each is its part's ERROR, rejected unseen, and so are the periods "
                               f"missed until a second of frames is read in time", time.time(), part_id, "behind")

    @staticmethod
    def _frame_before(unread: UnreadFrame) -> str:
        return unread.frame_id.rsplit("+", 1)[0]


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)
