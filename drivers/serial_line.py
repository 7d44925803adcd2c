"""A line-protocol link over pyserial for ``reject_scheduler``: ``REJECT P000012\\n`` style.

``send(line)`` writes the line and, when an acknowledgement is expected, reads the lines that arrive
after it until one matches it (``ack`` is compared after stripping; ``{part_id}`` etc. are already
filled in by the caller) or ``ack_timeout_s`` passes. Any pyserial URL works as the port: ``/dev/ttyUSB0``,
``/dev/pts/7`` (a socat pair), ``loop://`` (tests), ``socket://host:port``.

This module imports nothing from the rest of stereo-inspect.
"""
from __future__ import annotations

import time
from dataclasses import dataclass

from drivers.reject_scheduler import LinkError, LinkRefused

# the fastest USB serial adapters' rate: beyond it a port fails to open at every command ("invalid baudrate")
MAX_BAUDRATE = 12_000_000


@dataclass(frozen=True)
class LineCommand:
    text: str  # without the line ending
    ack: str | None = None  # expected reply line, None: do not wait


def _why(exc: Exception) -> str:
    """The operating system's reason under a pyserial error, which otherwise names the port twice more."""
    import serial

    inner = exc.__context__ if isinstance(exc, serial.SerialException) else exc
    if isinstance(inner, OSError) and not isinstance(inner, serial.SerialException) and inner.strerror:
        return inner.strerror
    return str(exc)


class SerialLine:
    def __init__(self, port: str, baudrate: int = 9600, parity: str = "N", stopbits: float = 1, bytesize: int = 8,
                 line_ending: str = "\n", ack_timeout_s: float = 0.5, encoding: str = "ascii"):
        self.port, self.baudrate, self.parity, self.stopbits, self.bytesize = port, baudrate, parity, stopbits, bytesize
        self.line_ending, self.ack_timeout_s, self.encoding = line_ending, ack_timeout_s, encoding
        self.serial = None

    def connect(self) -> None:
        import serial

        self.close()
        try:
            self.serial = serial.serial_for_url(
                self.port, baudrate=self.baudrate, parity=self.parity, stopbits=self.stopbits, bytesize=self.bytesize,
                timeout=0.05, write_timeout=1.0,
            )
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"cannot open serial port {self.port}: {_why(exc)}") from None
        self.serial.reset_input_buffer()

    def close(self) -> None:
        if self.serial is not None:
            try:
                self.serial.close()
            except Exception:
                pass
            self.serial = None

    def send(self, command: LineCommand) -> str:
        import serial

        if self.serial is None:
            raise LinkError(f"serial port {self.port} not open")
        try:
            if command.ack is not None:
                # whatever waits unread answers an earlier line: taken for this one's acknowledgement, a line
                # the device never confirmed would count as delivered
                self.serial.reset_input_buffer()
            self.serial.write((command.text + self.line_ending).encode(self.encoding))
            self.serial.flush()
            if command.ack is None:
                return ""
            return self._wait_ack(command.ack)
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise LinkError(f"{self.port}: {exc}") from None

    def _wait_ack(self, expected: str) -> str:
        end = time.monotonic() + self.ack_timeout_s
        buffer = b""
        seen: list[str] = []
        while time.monotonic() < end:
            chunk = self.serial.read(self.serial.in_waiting or 1)  # blocks up to the 50 ms port timeout
            if not chunk:
                continue
            buffer += chunk
            while b"\n" in buffer:
                raw, buffer = buffer.split(b"\n", 1)
                line = raw.decode(self.encoding, "replace").strip()
                if line == expected.strip():
                    return f"ack {line!r}"
                if line:
                    seen.append(line)
        if seen:  # the device answered, with something else: it refused the line, it is not away
            raise LinkRefused(f"{self.port}: answered {', '.join(repr(s) for s in seen[-3:])}, not the acknowledgement "
                              f"{expected.strip()!r}, within {self.ack_timeout_s * 1000:.0f} ms")
        raise LinkError(f"{self.port}: no acknowledgement {expected.strip()!r} within {self.ack_timeout_s * 1000:.0f} ms")
