"""A watch on the frames in inspection: one that does not finish in time means a stage or a plugin has
stopped returning (a driver deadlock, a hung GPU, a store on a dead disk).

Without it, a loop stuck inside a plugin call raises nothing: the camera keeps running, the outputs'
threads keep the PLC's ready coil on and its heartbeat beating, and the parts on the belt pass
uninspected. ``StallWatch`` calls ``on_stall`` once when a frame has been in inspection longer than its
limit (the oldest of them is named), and ``on_resume`` once every frame that was late has finished; the engine raises an
alarm and has its outputs tell the line it is not ready in between.

Time comes from ``clock`` (monotonic seconds); ``check()`` is one look at it, which a thread repeats
every quarter of the limit once ``start()`` is called, and which tests call themselves.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable


class StallWatch:
    """limit_s: how long a frame may be in inspection (``started`` may give one its own). on_stall(key, what,
    seconds): the oldest frame past its limit (its key and description) has been in inspection ``seconds``. on_resume(seconds): the stall is over,
    after ``seconds`` from its start."""

    def __init__(self, limit_s: float, on_stall: Callable[[str, str, float], None],
                 on_resume: Callable[[float], None], clock: Callable[[], float] = time.monotonic):
        if not limit_s > 0:
            raise ValueError(f"StallWatch: limit_s must be positive, got {limit_s}")
        self.limit_s = limit_s
        self._on_stall, self._on_resume, self._clock = on_stall, on_resume, clock
        self._lock = threading.Lock()
        self._started: dict[str, tuple[float, str, float]] = {}  # key -> (when it started, what it is, its limit)
        self._stalled_since: float | None = None
        self._closed = threading.Event()
        self._thread: threading.Thread | None = None

    def started(self, key: str, what: str, limit_s: float | None = None) -> None:
        """A frame entered inspection (thread-safe); ``limit_s`` in place of the watch's own, for this one."""
        with self._lock:
            self._started[key] = (self._clock(), what, self.limit_s if limit_s is None else limit_s)

    def finished(self, key: str) -> None:
        """A frame left inspection: stored and handed to the outputs, or abandoned (thread-safe)."""
        with self._lock:
            self._started.pop(key, None)
        if not self._closed.is_set():
            self.check()

    def check(self) -> None:
        """Call ``on_stall`` or ``on_resume`` where the frames in inspection say so (outside the lock:
        they talk to the outputs)."""
        now = self._clock()
        with self._lock:
            late = sorted((t0, key, what) for key, (t0, what, limit) in self._started.items() if now - t0 > limit)
            if late and self._stalled_since is None:
                t0, key, what = late[0]  # the oldest of those late
                self._stalled_since = t0
                stall = (key, what, now - t0)
            else:
                stall = None
            resumed = None
            if not late and self._stalled_since is not None:
                resumed, self._stalled_since = now - self._stalled_since, None
        if stall is not None:
            self._on_stall(*stall)
        if resumed is not None:
            self._on_resume(resumed)

    @property
    def stalled(self) -> bool:
        with self._lock:
            return self._stalled_since is not None

    def start(self) -> StallWatch:
        self._thread = threading.Thread(target=self._run, name="stall watch", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Stop watching (frames still in inspection are no longer timed)."""
        self._closed.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)

    def _run(self) -> None:
        # at least once a second: a frame may have a shorter limit of its own, and a wait too long to express
        # (limit_s 1e300) raised OverflowError in this thread, which then watched nothing
        while not self._closed.wait(min(self.limit_s / 4, 1.0)):
            self.check()
