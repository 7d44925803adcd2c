"""``core.frame_source``: every frame read is handed to the loop or given back by ``close()``, never lost."""
from __future__ import annotations

import threading
import time

import pytest

from core.frame_source import DetectAhead, OneAtATime


class Camera:
    """Frames 0, 1, 2, ... counted as they are read; ``block_after`` makes the read after that many wait
    for ``release`` (a hardware trigger that does not come)."""

    def __init__(self, count: int = 100, block_after: int | None = None):
        self.count, self.block_after = count, block_after
        self.read = 0
        self.release = threading.Event()

    def frames(self):
        for i in range(self.count):
            if self.block_after is not None and i >= self.block_after:
                self.release.wait()
            self.read += 1
            yield i


def detect(item):
    time.sleep(0.01)  # long enough for the loop to get ahead of the thread at times
    return f"detected {item}"


def make(kind, camera, limit=None):
    if kind == "ahead":
        return DetectAhead(camera.frames(), detect, limit, stop_wait_s=0.5)
    return OneAtATime(camera.frames(), limit)


@pytest.mark.parametrize("kind", ["ahead", "one"])
class TestStopReading:
    def test_every_frame_read_before_the_stop_is_handed_over(self, kind):
        camera = Camera()
        source = make(kind, camera)
        taken = []
        for item, detected in source:
            taken.append(item)
            assert detected == (f"detected {item}" if kind == "ahead" else None)
            if len(taken) == 3:
                time.sleep(0.2)  # the thread reads and detects the next two frames meanwhile
                source.stop_reading()
        assert source.close() == []
        # one at a time reads nothing after the stop; ahead, the frames it held then (one waiting, one detected)
        assert taken == list(range(camera.read))
        assert len(taken) == 3 if kind == "one" else 3 <= len(taken) <= 5

    def test_limit_reads_no_more_frames(self, kind):
        camera = Camera()
        source = make(kind, camera, limit=2)
        assert [item for item, _ in source] == [0, 1]
        source.close()
        assert camera.read == 2

    def test_the_end_of_the_frames_ends_the_iteration(self, kind):
        camera = Camera(count=3)
        source = make(kind, camera)
        assert [item for item, _ in source] == [0, 1, 2]
        assert source.close() == []


class TestDetectAhead:
    def test_a_stop_does_not_wait_for_a_camera_that_delivers_nothing(self):
        camera = Camera(block_after=2)
        source = DetectAhead(camera.frames(), detect, stop_wait_s=0.5)
        taken = []
        started = time.monotonic()
        for item, _ in source:
            taken.append(item)
            if len(taken) == 2:
                source.stop_reading()
        assert taken == [0, 1] and time.monotonic() - started < 2.0
        camera.release.set()  # the trigger comes after the stop: that frame is dropped unread
        assert source.close() == []
        assert not any(t.name == "detect-ahead" and t.is_alive() for t in threading.enumerate())

    def test_close_gives_back_what_the_loop_did_not_take(self):
        camera = Camera()
        source = DetectAhead(camera.frames(), detect, stop_wait_s=0.5)
        iterator = iter(source)
        assert next(iterator)[0] == 0
        time.sleep(0.1)  # frame 1 is read, detected and waiting
        left = source.close()  # the loop leaves (an exception, Ctrl-C) with frame 1 read
        assert [item for item, _ in left] == list(range(1, camera.read))
        assert left and all(detected == f"detected {item}" for item, detected in left)

    def test_a_camera_that_raises_raises_in_the_loop(self):
        def frames():
            yield 0
            raise OSError("USB device vanished")

        source = DetectAhead(frames(), detect)
        with pytest.raises(OSError, match="USB device vanished"):
            for _ in source:
                pass
        assert source.close() == []
