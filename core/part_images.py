"""The annotated images of a run's parts, saved beside its results store while the disk has room.

The decisions matter more than their pictures: a disk running out of space or an images folder that
cannot be written costs the pictures, with one alarm, and the run goes on storing and sending its
decisions. (A store that cannot write its decisions stops the run: ``core.engine``.)
"""
from __future__ import annotations

import contextlib
import shutil
import time
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from core.annotate import annotate
from core.types import Alarm, PartResult, Status

MB = 2**20


class PartImages:
    """Saves each part's annotated image as ``policy`` says (``rejected``, ``all`` or ``none``) into
    ``folder`` while the disk keeps ``min_free_mb`` free; ``save`` returns the alarm the first time it
    cannot, after which it saves none."""

    def __init__(self, folder: Path, policy: Literal["rejected", "all", "none"], min_free_mb: float):
        self.folder = Path(folder)
        self.policy = policy
        self.min_free_mb = float(min_free_mb)
        self.stopped: str | None = None  # why images are no longer saved

    def wanted(self, part: PartResult) -> bool:
        return self.policy == "all" or (self.policy == "rejected" and part.verdict.status.rejects)

    def save(self, image: np.ndarray | None, part: PartResult, defect_status: list[Status]) -> Alarm | None:
        """Write the part's annotated image and set ``part.image_path``, where wanted and still possible;
        the alarm that says images stop here, else None."""
        if image is None or self.stopped is not None or not self.wanted(part):
            return None
        path = self.folder / f"{part.part_id}.jpg"
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            free_mb = shutil.disk_usage(self.folder).free / MB
            if free_mb < self.min_free_mb:
                return self._stop(part, f"the results disk has {free_mb:.0f} MB free, less than results.min_free_mb "
                                        f"({self.min_free_mb:g})")
            ok, encoded = cv2.imencode(".jpg", annotate(image, part, defect_status))
            if not ok:
                return self._stop(part, f"{path} could not be encoded")
            path.write_bytes(encoded.tobytes())
        except Exception as exc:  # whatever it is, a picture is not worth the run
            with contextlib.suppress(OSError):
                path.unlink(missing_ok=True)  # what a full disk left of it
            reason = getattr(exc, "strerror", None) or exc
            return self._stop(part, f"{path} could not be written ({type(exc).__name__}: {reason})")
        part.image_path = str(path)
        return None

    def _stop(self, part: PartResult, why: str) -> Alarm:
        self.stopped = why
        return Alarm("store", f"annotated images are no longer saved: {why}; every part's decision is still stored "
                              f"and sent", time.time(), part.part_id, "images")
