"""Will the stereo stage fit in this machine's memory?

A matcher that holds a cost volume needs memory in proportion to the pixels times the disparities it
searches: torch_sgm on an HD1080 frame with a 240 px range may take 11 GiB. Beyond the memory the
machine has, the kernel kills the process: no exception, no alarm, the run left unfinished and the
rejects it had queued neither sent nor reported. So a backend may state what one map takes (the optional
``memory_bytes(height, width, disparities)`` of ``core.contracts.StereoBackend``), and the engine
refuses what cannot fit: a recipe whose whole frame cannot (``region: full``) before the run starts, a
crop that cannot as its part's ERROR.
"""
from __future__ import annotations

import math
from typing import Any

import psutil

from core.recipe import LoadedRecipe
from core.recipe.loader import camera_answer
from core.types import Calibration

GIB = 2**30


def available_bytes() -> int:
    """Memory the process can take without swapping (the kernel's estimate)."""
    return int(psutil.virtual_memory().available)


def needed_bytes(backend: Any, height: int, width: int, disparities: int) -> int | None:
    """What the backend states one ``height`` x ``width`` map over ``disparities`` takes, or None where it
    states nothing."""
    estimate = getattr(backend, "memory_bytes", None)
    return int(estimate(height, width, disparities)) if callable(estimate) else None


def memory_problem(backend: Any, height: int, width: int, disparities: int, available: int | None = None,
                   name: str = "the stereo backend") -> str | None:
    """A sentence where matching an ``height`` x ``width`` image over ``disparities`` would take more
    memory than is ``available`` (bytes; the machine's now if None), else None."""
    needed = needed_bytes(backend, height, width, disparities)
    if needed is None:
        return None
    available = available_bytes() if available is None else available
    if needed <= available:
        return None
    return (f"{name} would need {needed / GIB:.1f} GiB for a {width}x{height} image with "
            f"{disparities} disparities, and {available / GIB:.1f} GiB of memory is available")


def search_disparities(lo: float, hi: float) -> int:
    """The number of disparities a backend searches over ``lo <= d < hi``."""
    return max(1, math.ceil(hi - lo))


def whole_frame_problem(stereo: Any, backend: Any, calib: Calibration, available: int | None = None) -> str | None:
    """Where the recipe's whole frame (``calib``'s size, the ``stereo`` section's scale and search range)
    cannot be matched in the memory available, why and what would fit, else None."""
    lo, hi = stereo.search_range(calib)
    scale = min(1.0, stereo.scale)
    height, width = max(1, round(calib.height * scale)), max(1, round(calib.width * scale))
    width = max(1, width - math.floor(lo * scale))  # the columns that cannot match are not matched
    problem = memory_problem(backend, height, width, search_disparities(lo * scale, hi * scale), available,
                             stereo.backend)
    if problem is None:
        return None
    return (f"{problem} (the whole frame at stereo.scale {scale:g}): a lower stereo.scale (half of it needs an "
            f"eighth of the memory) or a narrower stereo.working_distance_mm needs less")


def recipe_problem(loaded: LoadedRecipe, backend: Any, registry: Any) -> str | None:
    """``whole_frame_problem`` for the geometry the recipe's camera states before it runs, None where it
    states none or the search range does not fit the image (the recipe's validation reports that)."""
    calib = camera_answer(loaded, registry, "calibration")
    if calib is None:
        return None
    try:
        return whole_frame_problem(loaded.recipe.stereo, backend, calib)
    except ValueError:
        return None
