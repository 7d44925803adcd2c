"""What the ``modbus`` and ``serial`` outputs share: when a reject is due, and turning the
scheduler's records into the engine's ``OutputEvent``s and ``Alarm``s.

Reject timing: the actuator sits downstream of the camera, so a part's command is due at
``part.timestamp + delay`` with ``delay = delay_ms`` or ``actuator_distance_mm / conveyor_speed_mm_s``.
A command that cannot be sent by ``due + max_late_ms`` is an alarm.
"""
from __future__ import annotations

from typing import Callable

from pydantic import Field, model_validator

from core.contracts import PluginContext
from core.settings_model import MAX_RECONNECT_MS, Settings
from core.types import Alarm, OutputEvent, PartResult
from drivers.reject_scheduler import Command, Record, RejectScheduler

MAX_CLOSE_WAIT_S = 120.0


class TimingSettings(Settings):
    delay_ms: float | None = Field(None, gt=0, description="fire this long after the part was captured")
    actuator_distance_mm: float | None = Field(None, gt=0, description="camera line to actuator, along the belt")
    conveyor_speed_mm_s: float | None = Field(None, gt=0, description="belt speed")
    max_late_ms: float = Field(100.0, gt=0, description="a command not sent by due + this is an alarm")
    reconnect_min_ms: float = Field(100.0, gt=0, le=MAX_RECONNECT_MS, description="first reconnect back-off")
    reconnect_max_ms: float = Field(2000.0, gt=0, le=MAX_RECONNECT_MS, description="longest reconnect back-off")

    @model_validator(mode="after")
    def _one_delay(self):
        by_distance = self.actuator_distance_mm is not None or self.conveyor_speed_mm_s is not None
        if by_distance and self.delay_ms is not None:
            raise ValueError("give either delay_ms or actuator_distance_mm with conveyor_speed_mm_s, not both")
        if by_distance and (self.actuator_distance_mm is None or self.conveyor_speed_mm_s is None):
            raise ValueError("actuator_distance_mm and conveyor_speed_mm_s go together")
        if not by_distance and self.delay_ms is None:
            # without one every command would be due at its part's capture, before the part is decided
            raise ValueError("give the time from the camera to the actuator: delay_ms, or actuator_distance_mm "
                             "with conveyor_speed_mm_s")
        if self.reconnect_max_ms < self.reconnect_min_ms:
            raise ValueError("reconnect_max_ms must be at least reconnect_min_ms")
        if self.delay_s > MAX_CLOSE_WAIT_S:
            # a speed in m/s where mm/s is meant gives such a delay: each reject would fire at another plate
            given = (f"{self.actuator_distance_mm:g} mm at {self.conveyor_speed_mm_s:g} mm/s" if self.delay_ms is None
                     else f"delay_ms {self.delay_ms:g}")
            raise ValueError(f"the actuator would be {self.delay_s:.0f} s after the camera ({given}): longer than the "
                             f"{MAX_CLOSE_WAIT_S:.0f} s a run's end waits for the plates on their way; check the "
                             f"units (mm, mm/s, ms)")
        return self

    @property
    def delay_s(self) -> float:
        if self.actuator_distance_mm is not None and self.conveyor_speed_mm_s is not None:
            return self.actuator_distance_mm / self.conveyor_speed_mm_s
        return (self.delay_ms or 0.0) / 1000.0


def actuator_delay(model: type[TimingSettings]) -> Callable[[dict, PluginContext], float]:
    """``PluginSpec.actuator_delay`` of an output whose settings are ``model``."""
    return lambda settings, ctx: model.model_validate(settings).delay_s


def late_limit(model: type[TimingSettings]) -> Callable[[dict, PluginContext], float]:
    """``PluginSpec.late_limit`` of an output whose settings are ``model``: its ``max_late_ms``."""
    return lambda settings, ctx: model.model_validate(settings).max_late_ms / 1000.0


class ScheduledOutput:
    """A ``RejectOutput`` over a ``RejectScheduler``; subclasses say what to send for a part."""

    name = "output"

    def __init__(self, settings: TimingSettings, scheduler: RejectScheduler):
        self.timing = settings
        self.scheduler = scheduler

    def command_for(self, part: PartResult) -> Command | None:
        raise NotImplementedError

    def submit(self, part: PartResult) -> None:
        command = self.command_for(part)
        if command is not None:
            self.scheduler.submit(part.part_id, command, part.timestamp + self.timing.delay_s)

    def poll(self) -> list[OutputEvent | Alarm]:
        return self._convert(self.scheduler.drain())

    def hold(self, reason: str) -> None:
        """The inspection has stalled (``reason``): the line is told it is not ready (the ready coil off, no
        heartbeat) until ``release``."""
        self.scheduler.hold()

    def release(self) -> None:
        self.scheduler.release()

    def close(self, timeout_s: float = 10.0) -> list[OutputEvent | Alarm]:
        """Plates still on their way to the actuator get their command: wait at least until the last
        one is due (plus ``max_late_ms`` and a margin), at most ``MAX_CLOSE_WAIT_S``."""
        wait = self.scheduler.last_due_in() + self.timing.max_late_ms / 1000.0 + 0.5
        try:
            records = self.scheduler.close(max(timeout_s, min(wait, MAX_CLOSE_WAIT_S)))
        except KeyboardInterrupt:
            # Ctrl-C again while plates are on their way: what is still queued is alarmed now, not dropped
            records = self.scheduler.close(0.0, "not sent: the run was stopped again (Ctrl-C) while its plate was "
                                                "on its way to the actuator")
        return self._convert(records)

    def _convert(self, records: list[Record]) -> list[OutputEvent | Alarm]:
        events: list[OutputEvent | Alarm] = []
        for r in records:
            events.append(OutputEvent(self.name, r.key, r.text, r.outcome, r.timestamp, r.detail))
            if r.alarm:
                events.append(Alarm(self.name, r.alarm, r.timestamp, r.key, r.cause))
        return events
