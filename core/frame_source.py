"""Where the run loop's frames come from: read one at a time, or read and detected one frame ahead.

Both hand the loop ``(frame, detected)`` pairs and stop the same way: ``stop_reading()`` ends the
reading of new frames, and every frame already read is still handed over, so a stop never leaves a part
read but not inspected. A frame the camera returns after the stop was asked for is dropped unread, as
the one-at-a-time reader would never have asked for it. ``close()`` returns what was read and could not
be handed over (the loop left early: an exception, a second Ctrl-C), for the loop to account for.
"""
from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterable, Iterator
from typing import Any

Entry = tuple[Any, Any]  # (StereoFrame | FrameError, Detected | None)


class OneAtATime:
    """Frames read when the loop asks for the next one; the loop's own thread detects them."""

    def __init__(self, frames: Iterable[Any], limit: int | None = None):
        self._frames = frames
        self._limit = limit
        self._stopped = False

    def __iter__(self) -> Iterator[Entry]:
        read = 0
        for item in self._frames:
            yield item, None
            read += 1
            if self._stopped or (self._limit is not None and read >= self._limit):
                return

    def stop_reading(self) -> None:
        self._stopped = True

    def close(self) -> list[Entry]:
        return []


class DetectAhead:
    """Frames read and detected in a second thread, one frame ahead of the loop: while the loop works on
    frame n (stereo, depth, store, outputs), frame n + 1 is read and detected. Torch and OpenCV release
    the GIL, so the two overlap where a core is free.

    frames: the camera's frames; detect: frame -> its ``Detected``; limit: read at most this many.
    A thread blocked inside the camera at ``close()`` (a reconnect back-off, a hardware trigger) is left
    after ``stop_wait_s``: the camera's own close ends it, and what it reads then is dropped unread."""

    def __init__(self, frames: Iterable[Any], detect: Callable[[Any], Any], limit: int | None = None,
                 stop_wait_s: float = 5.0):
        self._frames, self._detect, self._limit, self._stop_wait_s = frames, detect, limit, stop_wait_s
        self._ready: queue.Queue = queue.Queue(maxsize=1)
        self._lock = threading.Lock()
        self._stopped = False  # no new frames are read
        self._in_hand = False  # the thread holds a frame it read before the stop (detecting it, or waiting to hand it over)
        self._gone = threading.Event()  # the loop takes nothing more
        self._left: list[Entry] = []
        self._done = object()
        self._worker = threading.Thread(target=self._produce, name="detect-ahead", daemon=True)
        self._worker.start()

    def _produce(self) -> None:
        try:
            read, frames = 0, iter(self._frames)
            while True:
                with self._lock:
                    if self._stopped:
                        return
                try:
                    item = next(frames)
                except StopIteration:
                    return
                with self._lock:
                    if self._stopped:  # the camera returned after the stop was asked for
                        return
                    self._in_hand = True
                self._hand_over((item, self._detect(item)))
                read += 1
                if self._limit is not None and read >= self._limit:
                    return
        except BaseException as exc:  # a camera that raises: handed to the loop, which raises it there
            self._hand_over(_RaisedInReader(exc))
        finally:
            self._hand_over(self._done)

    def _hand_over(self, entry: Any) -> None:
        while not self._gone.is_set():
            try:
                self._ready.put(entry, timeout=0.1)
                break
            except queue.Full:
                continue
        else:
            if isinstance(entry, tuple):
                self._left.append(entry)
        with self._lock:
            self._in_hand = False

    def __iter__(self) -> Iterator[Entry]:
        while True:
            try:
                entry = self._ready.get(timeout=0.05)
            except queue.Empty:
                with self._lock:
                    # stopped, nothing waiting and nothing in hand: the thread is in the camera or done
                    if self._stopped and not self._in_hand and self._ready.empty():
                        return
                continue
            if entry is self._done:
                return
            if isinstance(entry, _RaisedInReader):
                raise entry.exc
            yield entry

    def stop_reading(self) -> None:
        with self._lock:
            self._stopped = True

    def close(self) -> list[Entry]:
        """End the thread; the frames it read that the loop did not take."""
        self.stop_reading()
        self._gone.set()
        self._worker.join(timeout=self._stop_wait_s)
        left = []
        while True:
            try:
                entry = self._ready.get_nowait()
            except queue.Empty:
                break
            if isinstance(entry, tuple):
                left.append(entry)
        left += self._left  # read after the one waiting in the queue
        self._left.clear()
        return left


class _RaisedInReader:
    """What the camera raised in the reading thread, carried to the loop to be raised there."""

    def __init__(self, exc: BaseException):
        self.exc = exc

