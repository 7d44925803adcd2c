"""A Modbus master link (TCP or RTU) for ``reject_scheduler``: one write per ``send``.

Commands are ``ModbusWrite(table, address, value, unit)`` with table ``coil`` or ``register``.
Failures raise ``LinkError`` with the reason (refused, timeout, exception code); the link then
drops the connection so that a late answer to an old request cannot be taken for a new one.

From a Python prompt::

    >>> from drivers.modbus_link import ModbusLink, ModbusWrite
    >>> link = ModbusLink(transport="tcp", host="127.0.0.1", port=5020)
    >>> link.connect(); link.send(ModbusWrite("coil", 0, 1, unit=1))

This module imports nothing from the rest of stereo-inspect.
"""
from __future__ import annotations

import ipaddress
import logging
import re
from dataclasses import dataclass

# Imported here, not on the first connect: pymodbus's packages import each other in a circle, and a first
# import in the scheduler's thread while another thread imports pymodbus.server (the in-process PLC
# simulator) deadlocks or finds a module half-initialised.
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ModbusException

from drivers.reject_scheduler import LinkError, LinkRefused

# the standard exception codes (Modbus application protocol, section 7), in the words a commissioning engineer
# acts on
MODBUS_EXCEPTIONS = {1: "it does not take this write (illegal function)",
                     2: "it has no such address (illegal data address)",
                     3: "it does not take this value (illegal data value)",
                     4: "it failed while doing it (server device failure)",
                     6: "it is busy (server device busy)",
                     10: "its gateway has no path to that unit (gateway path unavailable)",
                     11: "the unit behind its gateway did not answer (gateway target device failed to respond)"}
ADDRESS_HINT = "- check the recipe's address against the PLC's (Modbus addresses count from 0)"


def host_problem(host: str) -> str | None:
    """Why ``host`` is no TCP address a PLC can be reached at (an IP address or a host name), or None. The mistakes
    a recipe makes (a port or a scheme in it, an IPv4 address with a typo) would otherwise be found at the first
    connection, as a PLC that cannot be reached."""
    if not host:
        return "empty: give the PLC's IP address or host name"
    try:
        ipaddress.ip_address(host)
        return None
    except ValueError:
        pass
    if "://" in host or "/" in host:
        return f"{host!r} is a URL: give the PLC's address alone (its port is `port`)"
    if ":" in host:
        return f"{host!r}: give the port as `port`, not in the host (an IPv6 address is written without brackets)"
    if re.fullmatch(r"[0-9.]+", host):
        return f"{host!r} is not an IPv4 address (four numbers of 0-255)"
    if not re.fullmatch(r"[A-Za-z0-9_]([A-Za-z0-9_.-]{0,251}[A-Za-z0-9_])?", host) or ".." in host:
        return f"{host!r} is not a host name (letters, digits, '-' and '.')"
    return None


@dataclass(frozen=True)
class ModbusWrite:
    table: str  # "coil" or "register"
    address: int
    value: int
    unit: int = 1

    def describe(self) -> str:
        verb = "write_coil" if self.table == "coil" else "write_register"
        return f"{verb} {self.address} = {int(self.value)} unit {self.unit}"


class ModbusLink:
    def __init__(
        self,
        transport: str = "tcp",
        host: str = "127.0.0.1",
        port: int = 502,
        serial_port: str | None = None,
        baudrate: int = 19200,
        parity: str = "N",
        stopbits: int = 1,
        bytesize: int = 8,
        timeout_s: float = 0.3,
    ):
        if transport not in ("tcp", "rtu"):
            raise ValueError(f"transport must be tcp or rtu, not {transport!r}")
        if transport == "rtu" and not serial_port:
            raise ValueError("rtu needs a serial_port")
        self.transport, self.host, self.port = transport, host, int(port)
        self.serial_port, self.baudrate, self.parity, self.stopbits, self.bytesize = (
            serial_port, baudrate, parity, stopbits, bytesize)
        self.timeout_s = timeout_s
        self.client = None
        logging.getLogger("pymodbus").setLevel(logging.CRITICAL)  # no hex dumps on every failed request

    @property
    def where(self) -> str:
        return f"{self.host}:{self.port}" if self.transport == "tcp" else f"{self.serial_port} @ {self.baudrate} baud"

    def _make_client(self):
        if self.transport == "tcp":
            return ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0)
        return ModbusSerialClient(self.serial_port, baudrate=self.baudrate, parity=self.parity, stopbits=self.stopbits,
                                  bytesize=self.bytesize, timeout=self.timeout_s, retries=0)

    def connect(self) -> None:
        self.close()
        client = self._make_client()
        if not client.connect():
            client.close()
            raise LinkError(f"cannot connect to the PLC at {self.where}")
        self.client = client

    def close(self) -> None:
        if self.client is not None:
            try:
                self.client.close()
            finally:
                self.client = None

    def send(self, command: ModbusWrite) -> str:
        if self.client is None:
            raise LinkError(f"not connected to {self.where}")
        try:
            if command.table == "coil":
                response = self.client.write_coil(command.address, bool(command.value), device_id=command.unit)
            else:
                response = self.client.write_register(command.address, int(command.value) & 0xFFFF, device_id=command.unit)
        except (ModbusException, OSError) as exc:
            self.close()
            text = str(exc).replace("Modbus Error: ", "")
            raise LinkError(f"{self.where}: {text}") from None
        if response.isError():
            code = getattr(response, "exception_code", None)
            meaning = MODBUS_EXCEPTIONS.get(code, "an exception") if code is not None else "an exception"
            raise LinkRefused(f"{self.where}: the PLC refused {command.describe()}: {meaning} (Modbus exception "
                              f"{code}){' ' + ADDRESS_HINT if code == 2 else ''}")
        return ""

    def read(self, table: str, address: int, count: int = 1, unit: int = 1) -> list[int]:
        """Read coils or holding registers (commissioning help)."""
        if self.client is None:
            self.connect()
        if table == "coil":
            response = self.client.read_coils(address, count=count, device_id=unit)
            return [int(b) for b in response.bits[:count]]
        response = self.client.read_holding_registers(address, count=count, device_id=unit)
        return list(response.registers)
