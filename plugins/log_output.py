"""Reject output ``log``: writes the reject command it would send to a log file and/or the console.

Useful on a bench without a PLC, and as the simplest example of an output plugin.
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

from pydantic import Field, ValidationInfo, field_validator

from core.contracts import PluginContext, PluginSpec
from core.file_checks import unwritable
from core.hookspecs import hookimpl
from core.settings_model import Settings
from core.types import Alarm, OutputEvent, PartResult
from plugins.command_format import checked_format, command_text


class LogSettings(Settings):
    file: str | None = Field(None, description="append commands to this file (relative to the recipe)")
    on_pass: bool = Field(False, description="also log a PASS command for parts that pass")
    reject_format: str = "REJECT {part_id} {status}"
    pass_format: str = "PASS {part_id}"

    _formats = field_validator("reject_format", "pass_format")(checked_format)

    @field_validator("file")
    @classmethod
    def _writable(cls, value: str | None, info: ValidationInfo) -> str | None:
        """A file the commands cannot be appended to is said with the recipe, not as an alarm per reject."""
        recipe_dir = (info.context or {}).get("recipe_dir")
        if value is None or recipe_dir is None:
            return value
        path = Path(value).expanduser()
        problem = unwritable(path if path.is_absolute() else Path(recipe_dir) / path)
        if problem is not None:
            raise ValueError(f"cannot log to it: {problem}")
        return value


class LogOutput:
    name = "log"

    def __init__(self, settings: LogSettings, recipe_dir: Path):
        self.settings = settings
        self.logger = logging.getLogger("stereo_inspect.output.log")
        self.path = None
        if settings.file:
            self.path = Path(settings.file).expanduser()
            if not self.path.is_absolute():
                self.path = recipe_dir / self.path
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._events: list[OutputEvent | Alarm] = []

    def submit(self, part: PartResult) -> None:
        if part.verdict.status.rejects:
            command = command_text(self.settings.reject_format, part)
        elif self.settings.on_pass:
            command = command_text(self.settings.pass_format, part)
        else:
            return
        self.logger.info(command)
        outcome, detail = "delivered", ""
        if self.path is not None:
            try:
                with open(self.path, "a") as f:
                    f.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} {command}\n")
            except OSError as exc:
                outcome, detail = "failed", f"{self.path}: {exc.strerror}"
        self._events.append(OutputEvent(self.name, part.part_id, command, outcome, time.time(), detail))
        if outcome == "failed":
            self._events.append(Alarm(self.name, f"reject for {part.part_id} not logged: {detail}", time.time(), part.part_id))

    def poll(self) -> list[OutputEvent | Alarm]:
        events, self._events = self._events, []
        return events

    def close(self, timeout_s: float = 10.0) -> list[OutputEvent | Alarm]:
        return self.poll()


def _factory(settings: dict, ctx: PluginContext) -> LogOutput:
    return LogOutput(LogSettings.model_validate(settings, context={"recipe_dir": ctx.recipe_dir}), Path(ctx.recipe_dir))


@hookimpl
def stereo_inspect_outputs() -> list[PluginSpec]:
    return [
        PluginSpec(
            name="log",
            kind="output",
            factory=_factory,
            settings_model=LogSettings,
            description="logs the reject command (and optionally passes) to the log and a file",
        )
    ]
