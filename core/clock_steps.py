"""How far the system clock was set while a frame was inspected.

A frame's capture time is this computer's ``time.time()``, and the outputs time its reject from it (``due =
capture + delay``). Setting the clock between the frame's arrival and the hand-over of its part (an NTP step, an
operator) moves every ``time.time()`` after it but not the stamp: the reject would fire that much early or late,
at another plate, and count as on time. The monotonic clock is never set, so the change in the difference
between the two clocks from the frame's arrival to the hand-over is the step; the engine hands the outputs the
capture time on the clock as it now stands, and measures a frame's age on the clock as it stood at arrival.

A step between the capture and the frame's arrival cannot be told from a late frame, and is not corrected.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Hashable

# Two reads of the clocks a few microseconds apart, and NTP's slewing (at most 0.5 ms a second): not a step.
STEP_TOLERANCE_S = 0.002


class ClockSteps:
    """``arrived(key)`` when a frame reaches the loop; ``since(key)`` the seconds the wall clock was set by
    since then (0 within ``STEP_TOLERANCE_S``, or for a key never seen); ``clock_at_arrival(key)`` the wall clock
    without them; ``forget(key)`` once its part is handed over."""

    def __init__(self, wall: Callable[[], float] | None = None, monotonic: Callable[[], float] | None = None):
        # looked up when made, not when this module was imported: the clocks the process has then
        self._wall, self._monotonic = wall or time.time, monotonic or time.monotonic
        self._offsets: dict[Hashable, float] = {}

    def _offset(self) -> float:
        return self._wall() - self._monotonic()

    def arrived(self, key: Hashable) -> None:
        self._offsets[key] = self._offset()

    def since(self, key: Hashable) -> float:
        then = self._offsets.get(key)
        if then is None:
            return 0.0
        step = self._offset() - then
        return step if abs(step) > STEP_TOLERANCE_S else 0.0

    def clock_at_arrival(self, key: Hashable) -> Callable[[], float]:
        """``time.time()`` as the clock stood when ``key`` arrived: the one its camera stamped it on."""
        return lambda: self._wall() - self.since(key)

    def forget(self, key: Hashable) -> None:
        self._offsets.pop(key, None)
