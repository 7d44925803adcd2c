"""What a running inspection hands the operator view: its latest frame and its recent rejects.

The engine thread only swaps references under a lock, so a slow or absent browser costs the line
nothing. Drawing the boxes and JPEG-encoding happen in the server's threads, once per frame that a
browser actually asks for (shared by every browser that asks for the same frame).
"""
from __future__ import annotations

import threading
import time
from collections import Counter, OrderedDict, deque
from typing import Any

import cv2
import numpy as np

from core.annotate import annotate


class LiveFeed:
    def __init__(self, keep_rejects: int = 24, fps_window: int = 30):
        self._lock = threading.Lock()
        self._seq = 0
        self._latest: Any = None  # the engine's FrameOutcome of the newest part with an image
        self._latest_part: Any = None  # the newest part, with or without an image
        self._rejects: OrderedDict[str, Any] = OrderedDict()
        self._keep = keep_rejects
        self._times: deque[float] = deque(maxlen=fps_window)
        self._encoded: tuple[tuple[int, int], bytes] | None = None
        self._encode_lock = threading.Lock()
        self.encodes = 0  # frames drawn and encoded for browsers: none while nobody watches
        self.state = "starting"  # starting -> running -> finished
        self.recipe_name = ""
        # Kept here, not counted in the store per request: a GROUP BY over a shift's parts takes
        # half a second at 300,000 parts, twice a second per browser, on the line's own cores.
        self._verdicts: Counter[str] = Counter()
        self._rejects_per_class: Counter[str] = Counter()

    # -- engine side (called from the inspection thread) ------------------------------------
    def started(self, recipe_name: str) -> None:
        with self._lock:
            self.recipe_name = recipe_name
            self.state = "running"

    def part(self, outcome: Any) -> None:
        now = time.monotonic()
        with self._lock:
            self._seq += 1
            self._latest_part = outcome.part
            if outcome.image is not None:
                self._latest = outcome
            self._times.append(now)
            self._verdicts[outcome.part.verdict.status.value] += 1
            for measurement, status in zip(outcome.part.measurements, outcome.defect_status):
                if status.value == "REJECT":
                    self._rejects_per_class[measurement.detection.class_name] += 1
            if outcome.part.verdict.status.rejects and outcome.image is not None:
                self._rejects[outcome.part.part_id] = outcome
                while len(self._rejects) > self._keep:
                    self._rejects.popitem(last=False)

    def finished(self) -> None:
        with self._lock:
            self.state = "finished"

    # -- server side --------------------------------------------------------------------------
    @property
    def seq(self) -> int:
        return self._seq

    def fps(self) -> float:
        """Parts per second over the last few parts; 0 once the line has stood still for 2 s."""
        with self._lock:
            times = list(self._times)
        if len(times) < 2 or time.monotonic() - times[-1] > 2.0:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0]) if times[-1] > times[0] else 0.0

    def verdict_counts(self) -> tuple[dict[str, int], dict[str, int]]:
        """Parts per verdict and rejected defects per class since the run started."""
        with self._lock:
            return dict(self._verdicts), dict(self._rejects_per_class)

    def latest_part(self) -> Any:
        with self._lock:
            return self._latest_part

    def latest_jpeg(self, quality: int) -> tuple[int, bytes] | None:
        with self._lock:
            outcome, seq = self._latest, self._seq
        if outcome is None:
            return None
        with self._encode_lock:
            if self._encoded is not None and self._encoded[0] == (seq, quality):
                return seq, self._encoded[1]
            data = encode_jpeg(annotate(outcome.image, outcome.part, outcome.defect_status), quality)
            self._encoded = ((seq, quality), data)
            self.encodes += 1
        return seq, data

    def reject_jpeg(self, part_id: str, quality: int, width: int | None = None) -> bytes | None:
        with self._lock:
            outcome = self._rejects.get(part_id)
        if outcome is None:
            return None
        return encode_jpeg(annotate(outcome.image, outcome.part, outcome.defect_status), quality, width)


def encode_jpeg(image: np.ndarray, quality: int, width: int | None = None) -> bytes:
    if width is not None and 0 < width < image.shape[1]:
        height = max(1, round(image.shape[0] * width / image.shape[1]))
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()
