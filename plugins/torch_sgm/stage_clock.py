"""Where one map's time goes: seconds per stage of the pipeline, for ``inspect stereo --stages``."""
from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager, nullcontext

import torch


class StageClock:
    """Seconds spent in each named stage, in the order the stages first ran. On CUDA the device is
    synchronised at each stage's start and end, so that a stage is charged for its own kernels and not
    for those queued before it."""

    def __init__(self, device: torch.device | str = "cpu", clock=time.perf_counter):
        self.seconds: dict[str, float] = {}
        self._clock = clock
        self._cuda = torch.device(device).type == "cuda"

    @contextmanager
    def __call__(self, stage: str) -> Iterator[None]:
        self._sync()
        start = self._clock()
        try:
            yield
        finally:
            self._sync()
            self.seconds[stage] = self.seconds.get(stage, 0.0) + self._clock() - start

    def _sync(self) -> None:
        if self._cuda:
            torch.cuda.synchronize()


def untimed(stage: str):
    """The clock of a map nobody times."""
    return nullcontext()
