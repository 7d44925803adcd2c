"""The four plugin kinds, as the objects the engine talks to.

A plugin package provides *factories* (see ``core.hookspecs``); a factory receives the
recipe's ``settings`` mapping for that plugin (already validated against the plugin's
``settings_model`` when it declares one) and a ``PluginContext``, and returns one of these.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from core.types import Alarm, Calibration, Detection, FrameError, OutputEvent, PartResult, StereoFrame

PluginKind = Literal["camera", "stereo", "detector", "output"]
PLUGIN_KINDS: tuple[PluginKind, ...] = ("camera", "stereo", "detector", "output")


@dataclass
class PluginContext:
    """What a factory may need beyond its own settings."""

    recipe_dir: Path = field(default_factory=Path.cwd)
    recipe_name: str = ""
    device: str = "cpu"
    log: Callable[[str], None] = print
    # True where ``device`` is what ``auto`` found (CUDA where torch sees one) rather than a device the command
    # named: a plugin may then run work that goes faster elsewhere there (torch_sgm: small pairs on the CPU)
    device_auto: bool = False


@runtime_checkable
class Camera(Protocol):
    def frames(self) -> Iterator[StereoFrame | FrameError]:
        """Rectified pairs in order. A frame that cannot be delivered is a ``FrameError``, never skipped."""

    def close(self) -> None: ...


@runtime_checkable
class StereoBackend(Protocol):
    def compute(self, left: np.ndarray, right: np.ndarray, min_disp: float, max_disp: float) -> np.ndarray:
        """Disparity of the left image.

        left, right: HxWx3 uint8 BGR, rectified; the engine's copies, which the backend may change in place.
        Returns HxW float32 disparity in pixels, NaN where invalid (zero and below are taken as invalid too).
        Searches ``min_disp <= d < max_disp``:
        a map whose matches lie mostly outside that range (``core.checks.disparity_problem``) costs the part
        an ERROR.
        """

    # Optional: ``warm_up()``, called once before the first part, where the first call is slow (kernels
    # compiled, buffers allocated): otherwise the first part is late and trips the recipe's ``watchdog_s``.
    # Optional: ``memory_bytes(height, width, disparities) -> int``, the most host memory one map of that
    # size and search takes: a recipe whose frames cannot fit is refused before the run, a crop that cannot
    # is its part's ERROR, instead of the process being killed with rejects queued (``core.stereo_memory``).
    # Optional: ``compute_timed(left, right, min_disp, max_disp) -> (disparity, {stage: seconds})``, the
    # map and where its time went, stage by stage (``inspect stereo --stages``).


@runtime_checkable
class Detector(Protocol):
    class_names: list[str]

    def detect(self, image: np.ndarray) -> list[Detection]:
        """Defects in an HxWx3 uint8 BGR image, boxes in its pixel coordinates. The image is read-only: stereo
        and depth measure the same pixels afterwards (draw on a copy). Called once per part, in frame order
        (the recipe's master parts, ``verify.path``, first), and for nothing else."""

    # Optional: ``warm_up()``, called once before the first part, where the first call is slow (a model set
    # up): otherwise the first part is late and trips the recipe's ``watchdog_s``.


@runtime_checkable
class RejectOutput(Protocol):
    def submit(self, part: PartResult) -> None:
        """Hand over a decided part (the output's own copy). Must not block the inspection loop for long."""

    def poll(self) -> list[OutputEvent | Alarm]:
        """Events and alarms produced since the last call (the engine records them)."""

    def close(self, timeout_s: float = 10.0) -> list[OutputEvent | Alarm]:
        """Deliver or alarm everything still queued, then release the transport."""

    # Optional (the engine looks for them): ``hold(reason: str)`` when a part has been in inspection longer
    # than the recipe's ``watchdog_s`` (a stage or plugin is not returning): tell the line the inspection is
    # not ready (a ready signal off, a heartbeat stopped); ``release()`` once it runs again. Both are called
    # from the engine's watch thread and must not block.


PROTOCOLS: dict[str, type] = {"camera": Camera, "stereo": StereoBackend, "detector": Detector, "output": RejectOutput}


def missing_members(obj: Any, kind: str) -> list[str]:
    """The methods and attributes of ``kind``'s protocol that ``obj`` lacks (a plugin's factory that
    returned something else: every part would fail on it)."""
    protocol = PROTOCOLS[kind]
    methods = [n for n, v in vars(protocol).items() if callable(v) and not n.startswith("_")]
    attributes = list(getattr(protocol, "__annotations__", {}))
    return ([m for m in methods if not callable(getattr(obj, m, None))]
            + [a for a in attributes if not hasattr(obj, a)])


@dataclass
class PluginSpec:
    """One named implementation of a plugin kind, as returned by the registration hooks."""

    name: str
    kind: PluginKind
    factory: Callable[[dict[str, Any], PluginContext], Any]
    description: str = ""
    settings_model: type | None = None  # a pydantic model; unknown keys are rejected when given
    # Optional, cameras: the rectified geometry the camera will deliver, from its settings alone (no
    # device opened), so that ``inspect validate`` can tell what depth the recipe can resolve.
    calibration: Callable[[dict[str, Any], PluginContext], Calibration] | None = None
    # Optional, detectors: the class names the detector will report, from its settings alone, so that a
    # recipe's rules can be checked against them before a run (a misspelled class would never apply).
    class_names: Callable[[dict[str, Any], PluginContext], list[str]] | None = None
    # Optional, cameras: the frames per second the camera will deliver (None: as fast as it is read).
    frame_rate: Callable[[dict[str, Any], PluginContext], float | None] | None = None
    # Optional, outputs: seconds from a part's capture to its command at the actuator, from the settings
    # alone, so that a recipe whose delay is shorter than a frame period is refused and a frame older
    # than the delay is an ERROR (its part is past the actuator).
    actuator_delay: Callable[[dict[str, Any], PluginContext], float | None] | None = None
    # Optional, outputs: the shortest time between two parts' commands that the actuator can be given
    # apart (a reject pulse and the low after it), from the settings alone, so that a camera delivering
    # parts faster than that is warned of; None where any rate will do (a counter, a level).
    part_interval: Callable[[dict[str, Any], PluginContext], float | None] | None = None
    # Optional, outputs: how long after its due time a command is still sent and counted delivered, from the
    # settings alone, so that a limit reaching the plate after a part's own is warned of.
    late_limit: Callable[[dict[str, Any], PluginContext], float | None] | None = None
    # Optional, any kind: what the settings let through without an error, from the settings alone, as (settings
    # key, warning) pairs that ``inspect validate`` and ``inspect run`` print under that key (a detector made to
    # see too little to find a defect, say, whose parts then pass).
    warnings: Callable[[dict[str, Any], PluginContext], list[tuple[str, str]]] | None = None

    def answer(self, question: str, settings: dict[str, Any], recipe_dir: Path) -> Any:
        """The answer to one of the optional questions above (``calibration``, ``frame_rate``, ...) from the
        plugin's ``settings`` alone; None where it has none or cannot give one."""
        ask = getattr(self, question)
        if ask is None:
            return None
        try:
            return ask(settings, PluginContext(recipe_dir=recipe_dir))
        except Exception:
            return None
