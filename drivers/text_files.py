"""Text files as editors save them: UTF-8, with or without the byte-order mark a Windows editor writes.

This module imports nothing from the rest of stereo-inspect.
"""
from __future__ import annotations


class NotUtf8(ValueError):
    """A byte that is not UTF-8: ``line`` (from 1) and ``byte`` say where and which."""

    def __init__(self, line: int, byte: int):
        super().__init__(f"not UTF-8 text (byte 0x{byte:02x})")
        self.line, self.byte = line, byte


def decode(data: bytes) -> str:
    """``data`` as text, a leading byte-order mark read past; ``NotUtf8`` at its first byte that is not UTF-8."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise NotUtf8(data[: exc.start].count(b"\n") + 1, data[exc.start]) from None
