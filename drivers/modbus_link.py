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

import logging
from dataclasses import dataclass

from drivers.reject_scheduler import LinkError


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
            from pymodbus.client import ModbusTcpClient

            return ModbusTcpClient(self.host, port=self.port, timeout=self.timeout_s, retries=0)
        from pymodbus.client import ModbusSerialClient

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
        from pymodbus.exceptions import ModbusException

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
            raise LinkError(f"{self.where}: PLC answered with an exception ({response})")
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
