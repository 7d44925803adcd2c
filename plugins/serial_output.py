"""Reject output ``serial``: sends a text line per part over a serial port (pyserial), at the time
the part reaches the actuator, optionally waiting for an acknowledgement line.

Recipe example::

    outputs:
      - plugin: serial
        settings:
          port: /dev/ttyUSB0        # any pyserial URL: /dev/pts/7, loop://, socket://host:port
          baudrate: 9600
          reject_format: "REJECT {part_id}"
          pass_format: null         # e.g. "PASS {part_id}"
          ack_format: "ACK {part_id}"  # null: do not wait for an answer
          ack_timeout_ms: 300
          delay_ms: 1500

Fields in the formats: ``{part_id}``, ``{status}`` (PASS/REJECT/ERROR/FLAG), ``{frame_id}``, ``{index}``
(``plugins.command_format``).
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from core.contracts import PluginContext, PluginSpec
from core.hookspecs import hookimpl
from core.types import PartResult
from drivers.reject_scheduler import Command, RejectScheduler
from drivers.serial_line import MAX_BAUDRATE, LineCommand, SerialLine
from plugins.command_format import checked_format, command_text
from plugins.reject_timing import ScheduledOutput, TimingSettings, actuator_delay, late_limit


class SerialSettings(TimingSettings):
    port: str = Field(min_length=1, description="serial port or pyserial URL")
    baudrate: int = Field(9600, gt=0, le=MAX_BAUDRATE)
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    bytesize: Literal[7, 8] = 8
    line_ending: Literal["\n", "\r\n", "\r"] = "\n"
    reject_format: str = "REJECT {part_id}"
    pass_format: str | None = None
    ack_format: str | None = None
    # at most 10 s: while a line waits for its answer, every later command waits behind it, unalarmed
    ack_timeout_ms: float = Field(300.0, gt=0, le=10000)

    _formats = field_validator("reject_format", "pass_format", "ack_format")(checked_format)

    @field_validator("reject_format", "pass_format", "ack_format")
    @classmethod
    def _one_ascii_line(cls, value: str | None) -> str | None:
        """The line goes out as ASCII: a format it cannot encode failed at every reject, and a line break in
        it would make two lines of one command."""
        if value is None:
            return None
        odd = [c for c in value if not c.isascii()]
        if odd:
            raise ValueError(f"bad format {value!r}: {odd[0]!r} is not ASCII, which the serial line sends")
        if "\n" in value or "\r" in value:
            raise ValueError(f"bad format {value!r}: a line break would send two lines for one part")
        return value


class SerialOutput(ScheduledOutput):
    name = "serial"

    def __init__(self, settings: SerialSettings):
        self.settings = settings
        line = SerialLine(settings.port, settings.baudrate, settings.parity, settings.stopbits, settings.bytesize,
                          settings.line_ending, ack_timeout_s=settings.ack_timeout_ms / 1000.0)
        scheduler = RejectScheduler(
            line, self.name, max_late_s=settings.max_late_ms / 1000.0,
            reconnect_min_s=settings.reconnect_min_ms / 1000.0, reconnect_max_s=settings.reconnect_max_ms / 1000.0,
            where=f"the serial line {settings.port}",
        )
        super().__init__(settings, scheduler)

    def command_for(self, part: PartResult) -> Command | None:
        fmt = self.settings.reject_format if part.verdict.status.rejects else self.settings.pass_format
        if fmt is None:
            return None
        text = command_text(fmt, part)
        ack = command_text(self.settings.ack_format, part) if self.settings.ack_format else None
        return Command(LineCommand(text, ack), f"serial {text!r}" + (f" (ack {ack!r})" if ack else ""))


def _factory(settings: dict, ctx: PluginContext) -> SerialOutput:
    return SerialOutput(SerialSettings.model_validate(settings))


@hookimpl
def stereo_inspect_outputs() -> list[PluginSpec]:
    return [
        PluginSpec(
            name="serial",
            kind="output",
            factory=_factory,
            settings_model=SerialSettings,
            actuator_delay=actuator_delay(SerialSettings),
            late_limit=late_limit(SerialSettings),
            description="reject via a text line on a serial port (e.g. 'REJECT <part_id>'), optional acknowledgement",
        )
    ]
