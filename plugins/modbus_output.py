"""Reject output ``modbus``: writes a coil pulse or a holding register on the PLC, at the time the
part reaches the actuator, over Modbus TCP or Modbus RTU (serial).

Recipe example::

    outputs:
      - plugin: modbus
        settings:
          transport: tcp            # or rtu with serial_port, baudrate, parity, stopbits
          host: 127.0.0.1
          port: 5020
          unit: 1
          on_reject: {write: coil, address: 0, pulse_ms: 200}   # or {write: counter, address: 20}
          on_pass: null             # or e.g. {write: register, address: 10, value: 1}
          actuator_distance_mm: 600 # or delay_ms: 1500
          conveyor_speed_mm_s: 400
          max_late_ms: 100
          ready_coil: 1             # set while the inspection is connected
          heartbeat: {address: 100, period_ms: 1000}
"""
from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator, model_validator

from core.contracts import PluginContext, PluginSpec
from core.hookspecs import hookimpl
from core.settings_model import Settings
from core.types import PartResult
from drivers.modbus_link import ModbusLink, ModbusWrite, host_problem
from drivers.reject_scheduler import MIN_PULSE_GAP_S, Command, RejectScheduler
from drivers.serial_line import MAX_BAUDRATE
from plugins.reject_timing import ScheduledOutput, TimingSettings, actuator_delay, late_limit


class WriteAction(Settings):
    """``coil``: set the coil to ``value`` (1), and back after ``pulse_ms`` when given;
    ``register``: write ``value`` into the holding register;
    ``counter``: write 1, 2, 3, ... (mod 65536) into the holding register, one step per part, so that
    the PLC sees every part even when parts come closer together than a coil pulse."""

    write: Literal["coil", "register", "counter"] = "coil"
    address: int = Field(0, ge=0, le=65535)
    value: int = Field(1, ge=0, le=65535)
    pulse_ms: float | None = Field(None, gt=0, description="coil only: reset the coil after this long (at least "
                                   f"{MIN_PULSE_GAP_S * 1000:g} ms, a PLC scan)")

    @model_validator(mode="after")
    def _check(self):
        if self.write == "coil" and self.value not in (0, 1):
            raise ValueError("a coil value is 0 or 1")
        if self.write != "coil" and self.pulse_ms is not None:
            raise ValueError("pulse_ms applies to a coil")
        if self.pulse_ms is not None and self.pulse_ms < MIN_PULSE_GAP_S * 1000:
            # a PLC reads its coils once a scan: a shorter high can fall between two reads, and the reject is lost
            raise ValueError(f"pulse_ms {self.pulse_ms:g}: shorter than the {MIN_PULSE_GAP_S * 1000:g} ms a PLC needs "
                             f"to see the coil high (one scan); give at least that, or write a counter")
        return self


class HeartbeatSettings(Settings):
    address: int = Field(ge=0, le=65535, description="holding register that receives a counter")
    period_ms: float = Field(1000.0, ge=50, le=60000)  # a PLC's watchdog counts beats seconds apart, not hours


class ModbusSettings(TimingSettings):
    transport: Literal["tcp", "rtu"] = "tcp"
    host: str = "127.0.0.1"
    port: int = Field(502, ge=1, le=65535)
    serial_port: str | None = Field(None, description="rtu: the serial port (/dev/ttyUSB0)")
    baudrate: int = Field(19200, gt=0, le=MAX_BAUDRATE)
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    unit: int = Field(1, ge=0, le=247, description="Modbus unit/device id")
    # at most 10 s: while a request waits, every later command waits behind it, unalarmed
    timeout_ms: float = Field(300.0, gt=0, le=10000, description="wait this long for the PLC to answer one request")
    on_reject: WriteAction = Field(default_factory=lambda: WriteAction(write="coil", address=0, value=1, pulse_ms=200))
    on_pass: WriteAction | None = None
    ready_coil: int | None = Field(None, ge=0, le=65535, description="coil set to 1 while connected, 0 on close")
    heartbeat: HeartbeatSettings | None = None

    @field_validator("host")
    @classmethod
    def _an_address(cls, value: str) -> str:
        problem = host_problem(value)
        if problem is not None:
            raise ValueError(problem)
        return value

    @model_validator(mode="after")
    def _transport(self):
        if self.transport == "rtu" and not self.serial_port:
            raise ValueError("transport rtu needs serial_port")
        if self.transport == "rtu" and self.unit == 0:
            raise ValueError("unit 0 is the RTU broadcast address: every device on the bus takes the write and none "
                             "answers, so no reject could be confirmed; give the PLC's own unit id (1-247)")
        return self

    @model_validator(mode="after")
    def _addresses(self):
        """Two signals on one coil or register: the PLC could not tell them apart (a pass read as a reject,
        the ready signal holding the gate's coil on). A reject and a pass may share one address only as
        different values of a level (not a counter, not pulsed)."""
        writes = [(key, action) for key, action in (("on_reject", self.on_reject), ("on_pass", self.on_pass))
                  if action is not None]
        for key, action in writes:
            table = "coil" if action.write == "coil" else "register"
            if table == "coil" and action.address == self.ready_coil:
                raise ValueError(f"{key} writes coil {action.address}, which is also ready_coil")
            if table == "register" and self.heartbeat is not None and action.address == self.heartbeat.address:
                raise ValueError(f"{key} writes register {action.address}, which is also heartbeat.address")
        if len(writes) == 2:
            (_, reject), (_, passed) = writes
            table = "coil" if reject.write == "coil" else "register"
            if (table == "coil") == (passed.write == "coil") and reject.address == passed.address:
                if "counter" in (reject.write, passed.write) or reject.value == passed.value:
                    raise ValueError(f"on_reject and on_pass both write to {table} {reject.address} "
                                     f"({reject.write} {reject.value}, {passed.write} {passed.value}): the PLC "
                                     f"could not tell a pass from a reject")
                if reject.pulse_ms or passed.pulse_ms:
                    raise ValueError(f"on_reject and on_pass both write to {table} {reject.address}, one of them "
                                     f"pulsed: a pass could cut short the pulse of the reject before it")
        return self


def part_interval(settings: dict, ctx: PluginContext) -> float | None:
    """``PluginSpec.part_interval``: a pulsed coil's pulse and the low the PLC needs before the next one."""
    model = ModbusSettings.model_validate(settings)
    pulses = [a.pulse_ms for a in (model.on_reject, model.on_pass) if a is not None and a.pulse_ms]
    return max(pulses) / 1000.0 + MIN_PULSE_GAP_S if pulses else None


def make_command(action: WriteAction, unit: int, count: int = 0) -> Command:
    if action.write == "counter":
        write = ModbusWrite("register", action.address, count & 0xFFFF, unit)
        return Command(write, f"{write.describe()} (part counter)")
    write = ModbusWrite(action.write, action.address, action.value, unit)
    if action.write == "coil" and action.pulse_ms:
        release = ModbusWrite("coil", action.address, 1 - action.value, unit)
        return Command(write, f"{write.describe()} (pulse {action.pulse_ms:g} ms)",
                       follow_up=Command(release, f"{release.describe()} (end of pulse)"),
                       follow_up_after_s=action.pulse_ms / 1000.0)
    return Command(write, write.describe())


def rest_commands(settings: ModbusSettings) -> list[Command]:
    """The pulsed coils the output owns, written back to rest: sent on every (re)connect, before anything
    else, so that the next pulse's rising edge is written to a coil known to be low."""
    commands = []
    for action in (settings.on_reject, settings.on_pass):
        if action is not None and action.write == "coil" and action.pulse_ms:
            rest = ModbusWrite("coil", action.address, 1 - action.value, settings.unit)
            commands.append(Command(rest, f"{rest.describe()} (at rest)"))
    return commands


class ModbusOutput(ScheduledOutput):
    name = "modbus"

    def __init__(self, settings: ModbusSettings):
        self.settings = settings
        link = ModbusLink(settings.transport, settings.host, settings.port, settings.serial_port, settings.baudrate,
                          settings.parity, settings.stopbits, timeout_s=settings.timeout_ms / 1000.0)
        unit = settings.unit
        ready = close = heartbeat = None
        if settings.ready_coil is not None:
            on = ModbusWrite("coil", settings.ready_coil, 1, unit)
            off = ModbusWrite("coil", settings.ready_coil, 0, unit)
            ready, close = Command(on, f"{on.describe()} (system ready)"), Command(off, f"{off.describe()} (system stopped)")
        if settings.heartbeat is not None:
            address = settings.heartbeat.address

            def heartbeat(n: int) -> Command:
                write = ModbusWrite("register", address, n & 0xFFFF, unit)
                return Command(write, f"{write.describe()} (heartbeat)")

        scheduler = RejectScheduler(
            link, self.name, max_late_s=settings.max_late_ms / 1000.0,
            reconnect_min_s=settings.reconnect_min_ms / 1000.0, reconnect_max_s=settings.reconnect_max_ms / 1000.0,
            on_connect=ready, on_close=close, heartbeat=heartbeat, idle=rest_commands(settings), where=f"the PLC at {link.where}",
            heartbeat_period_s=(settings.heartbeat.period_ms / 1000.0) if settings.heartbeat else 1.0,
        )
        super().__init__(settings, scheduler)
        self._counts = {"reject": 0, "pass": 0}

    def command_for(self, part: PartResult) -> Command | None:
        which = "reject" if part.verdict.status.rejects else "pass"
        action = self.settings.on_reject if which == "reject" else self.settings.on_pass
        if action is None:
            return None
        self._counts[which] += 1
        return make_command(action, self.settings.unit, self._counts[which])


def _factory(settings: dict, ctx: PluginContext) -> ModbusOutput:
    return ModbusOutput(ModbusSettings.model_validate(settings))


@hookimpl
def stereo_inspect_outputs() -> list[PluginSpec]:
    return [
        PluginSpec(
            name="modbus",
            kind="output",
            factory=_factory,
            settings_model=ModbusSettings,
            actuator_delay=actuator_delay(ModbusSettings),
            late_limit=late_limit(ModbusSettings),
            part_interval=part_interval,
            description="reject via Modbus TCP/RTU: coil pulse or register write at the actuator's due time",
        )
    ]
