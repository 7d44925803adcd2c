"""A Modbus server that stands in for the conveyor PLC (TCP and/or RTU over a serial port).

It keeps 1024 coils, discrete inputs, holding and input registers (addresses 0..1023) for
every unit id, and reports every coil or register *change* as a line
``HH:MM:SS.mmm coil 0 -> 1`` (``unit N`` is added when it is not 1). Each write is also kept in
``handle.writes`` so a test can check what arrived and when.

From a Python prompt::

    >>> from drivers import plc_sim
    >>> sim = plc_sim.serve_in_thread("127.0.0.1", 5020)      # prints each change
    >>> sim.coil(0), sim.register(10)
    >>> sim.stop()

``delay_s`` makes the simulated PLC slow to answer (a fault test). This module imports nothing
from the rest of stereo-inspect.
"""
from __future__ import annotations

import asyncio
import datetime as _dt
import logging
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

# Imported here, once, by whoever imports this module: pymodbus's packages import each other in a circle,
# and two threads importing them for the first time at once (the simulator starting while an output's
# thread connects) deadlock or find a module half-initialised.
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

SIZE = 1024  # addresses 0..SIZE-1 of each table

_COIL_WRITES = {5, 15}
_REGISTER_WRITES = {6, 16, 22, 23}


def quiet_pymodbus() -> None:
    """pymodbus logs every failed request with a hex dump; keep only its critical messages."""
    logging.getLogger("pymodbus").setLevel(logging.CRITICAL)


def stamp(t: float | None = None) -> str:
    """``HH:MM:SS.mmm`` in local time."""
    t = time.time() if t is None else t
    return _dt.datetime.fromtimestamp(t).strftime("%H:%M:%S.%f")[:-3]


def is_listening(host: str, port: int, timeout_s: float = 0.3) -> bool:
    """True when something accepts TCP connections on ``host:port``."""
    try:
        with socket.create_connection((host, int(port)), timeout=timeout_s):
            return True
    except OSError:
        return False


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port nothing listens on right now (for tests and demos)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


@dataclass(frozen=True)
class Write:
    """One write request the simulator received."""

    timestamp: float
    unit: int
    table: str  # "coil" or "register"
    address: int
    value: int


class PlcState:
    """Shadow copy of the tables, per unit, fed by the server's write callback."""

    def __init__(self, on_change: Callable[[str], None] | None):
        self.on_change = on_change
        self.lock = threading.Lock()
        self.coils: dict[tuple[int, int], int] = {}
        self.registers: dict[tuple[int, int], int] = {}
        self.writes: list[Write] = []
        self.delay_s = 0.0
        self.last_unit = 0  # unit id of the request being handled (from the server's PDU trace)

    def trace_pdu(self, sending: bool, pdu):
        if not sending:
            self.last_unit = int(getattr(pdu, "dev_id", 0) or 0)
        return pdu

    def record(self, unit: int, table: str, address: int, values: list[int]) -> None:
        now = time.time()
        lines = []
        with self.lock:
            store = self.coils if table == "coil" else self.registers
            for offset, value in enumerate(values):
                addr, value = address + offset, int(value)
                self.writes.append(Write(now, unit, table, addr, value))
                old = store.get((unit, addr), 0)
                store[(unit, addr)] = value
                if old != value:
                    where = f"{table} {addr}" if unit in (0, 1) else f"unit {unit} {table} {addr}"
                    lines.append(f"{stamp(now)} {where} -> {value}")
        if self.on_change is not None:
            for line in lines:
                try:
                    self.on_change(line)
                except Exception:  # a broken printer must not take the PLC down
                    logging.getLogger(__name__).exception("plc_sim on_change failed")


def _build_server_device(state: PlcState, unit_ids: tuple[int, ...] | None):
    def tables():
        return (
            [SimData(0, count=SIZE, values=False, datatype=DataType.BITS)],
            [SimData(0, count=SIZE, values=False, datatype=DataType.BITS)],
            [SimData(0, count=SIZE, values=0, datatype=DataType.REGISTERS)],
            [SimData(0, count=SIZE, values=0, datatype=DataType.REGISTERS)],
        )

    def make_action(unit: int):
        async def action(function_code, start_address, address, count, registers, values):
            if state.delay_s > 0:
                await asyncio.sleep(state.delay_s)
            if values is not None:
                unit_id = unit or state.last_unit
                vals = values if isinstance(values, list) else [values]
                if function_code in _COIL_WRITES:
                    state.record(unit_id, "coil", address, [1 if v else 0 for v in vals])
                elif function_code in _REGISTER_WRITES:
                    state.record(unit_id, "register", address, [int(v) for v in vals])
            return None

        return action

    ids = unit_ids or (0,)  # id 0: answers every unit id
    return [SimDevice(id=i, simdata=tables(), action=make_action(i)) for i in ids]


class PlcSimulator:
    """A running simulator: ``stop()``, ``coil(addr)``, ``register(addr)``, ``writes``."""

    def __init__(self, state: PlcState, loop: asyncio.AbstractEventLoop, thread: threading.Thread, servers: list, label: str):
        self.state, self._loop, self._thread, self._servers, self.label = state, loop, thread, servers, label

    @property
    def writes(self) -> list[Write]:
        with self.state.lock:
            return list(self.state.writes)

    def coil(self, address: int, unit: int = 1) -> int:
        with self.state.lock:
            return self.state.coils.get((unit, address), 0)

    def register(self, address: int, unit: int = 1) -> int:
        with self.state.lock:
            return self.state.registers.get((unit, address), 0)

    def set_delay(self, seconds: float) -> None:
        """Answer every request ``seconds`` late (simulates a slow or overloaded PLC)."""
        self.state.delay_s = max(0.0, float(seconds))

    def stop(self, timeout_s: float = 3.0) -> None:
        if not self._thread.is_alive():
            return

        async def shutdown():
            for server in self._servers:
                await server.shutdown()

        try:
            asyncio.run_coroutine_threadsafe(shutdown(), self._loop).result(timeout_s)
        except Exception:
            pass
        self._thread.join(timeout_s)

    def __enter__(self) -> PlcSimulator:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def _start(
    host: str | None,
    port: int | None,
    rtu: str | None,
    on_change: Callable[[str], None] | None,
    *,
    baudrate: int = 19200,
    unit_ids: tuple[int, ...] | None = None,
    delay_s: float = 0.0,
) -> PlcSimulator:
    quiet_pymodbus()
    state = PlcState(on_change)
    state.delay_s = delay_s
    started = threading.Event()
    box: dict = {}

    async def main():
        servers = []
        try:
            if port is not None:
                box["where"] = f"{host or '127.0.0.1'}:{port}"
                tcp = ModbusTcpServer(_build_server_device(state, unit_ids), address=(host or "127.0.0.1", int(port)),
                                      trace_pdu=state.trace_pdu)
                await tcp.serve_forever(background=True)
                servers.append(tcp)
            if rtu:
                box["where"] = rtu
                serial_server = ModbusSerialServer(
                    _build_server_device(state, unit_ids), port=rtu, baudrate=baudrate, timeout=0.5, reconnect_delay=0.5,
                    trace_pdu=state.trace_pdu,
                )
                await serial_server.serve_forever(background=True)
                servers.append(serial_server)
        except Exception as exc:  # bind error, bad serial port, ...
            box["error"] = exc
            for server in servers:
                await server.shutdown()
            started.set()
            return
        box["servers"] = servers
        box["done"] = asyncio.get_running_loop().create_future()
        started.set()
        await asyncio.gather(*(server.serving for server in servers))

    loop = asyncio.new_event_loop()

    def run():
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(main())
            pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
            for task in pending:  # requests still being answered (slow mode)
                task.cancel()
            if pending:
                loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
        finally:
            loop.close()

    thread = threading.Thread(target=run, name=f"plc-sim {host}:{port}", daemon=True)
    thread.start()
    if not started.wait(10.0):
        raise RuntimeError("PLC simulator did not start within 10 s")
    if "error" in box:
        thread.join(2.0)
        raise OSError(f"PLC simulator cannot serve on {box['where']}: {box['error']}")
    if port is not None and not _wait_listening(host or "127.0.0.1", int(port), 3.0):
        raise OSError(f"PLC simulator does not listen on {host}:{port}")
    parts = ([f"tcp {host}:{port}"] if port is not None else []) + ([f"rtu {rtu}"] if rtu else [])
    return PlcSimulator(state, loop, thread, box["servers"], ", ".join(parts))


def _wait_listening(host: str, port: int, timeout_s: float) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if is_listening(host, port, 0.2):
            return True
        time.sleep(0.02)
    return False


def serve_in_thread(host: str, port: int, on_change: Callable[[str], None] = print, **options) -> PlcSimulator:
    """Start the simulator on ``host:port`` (Modbus TCP) in a background thread; returns once it listens.

    options: ``rtu`` (serial port path to also serve Modbus RTU on), ``baudrate``,
    ``unit_ids`` (default: answer every unit id), ``delay_s`` (answer late).
    """
    rtu = options.pop("rtu", None)
    return _start(host, port, rtu, on_change, **options)


def serve_rtu_in_thread(path: str, on_change: Callable[[str], None] = print, **options) -> PlcSimulator:
    """Start the simulator as a Modbus RTU slave on the serial port ``path`` only."""
    return _start(None, None, path, on_change, **options)
