"""Writing a whole file, with the file named when it cannot be: a full disk says so only at the write, and
Python's error then carries no file name (``error: No space left on device``, which of them?). What a
failed write left behind is removed, so that a file cut short is not read later as a whole one."""
from __future__ import annotations

import contextlib
from pathlib import Path


def write_bytes(path: Path, data: bytes) -> None:
    """``path`` holds ``data``; OSError("PATH: could not be written (why)") where it cannot."""
    path = Path(path)
    try:
        path.write_bytes(data)
    except OSError as exc:
        if path.is_symlink() or path.is_file():  # never a device itself, such as /dev/full
            with contextlib.suppress(OSError):
                path.unlink()
        raise OSError(f"{path}: could not be written ({exc.strerror or exc})") from None


def write_text(path: Path, text: str) -> None:
    """``write_bytes`` of ``text`` in UTF-8."""
    write_bytes(path, text.encode("utf-8"))
