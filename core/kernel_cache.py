"""A folder numba can keep the compiled kernels in, where it would find none and fail.

numba keeps a kernel's machine code beside its source (``__pycache__``) or, where the code's folder cannot be
written (an install owned by root and run by a service user, docs/hardware.md), in the user's cache folder
(``$XDG_CACHE_HOME`` or ``~/.cache``, then ``numba``). Where neither can be written (a system user without a home)
the import of the first module with a cached kernel failed ("cannot cache function ...: no locator available"), and
``inspect`` with a traceback. ``inspect`` therefore names a folder in the machine's temporary one in
``NUMBA_CACHE_DIR`` before any kernel is imported (``ensure``), and says so.
"""
from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import MutableMapping
from pathlib import Path

CODE = Path(__file__).resolve().parent  # core/: where numba would keep depth's kernels, in its __pycache__


def writable(folder: Path) -> bool:
    """Whether ``folder`` exists or can be made, and a file can be written in it (numba's own test)."""
    try:
        os.makedirs(folder, exist_ok=True)
        tempfile.TemporaryFile(dir=folder).close()
    except OSError:
        return False
    return True


def user_cache(environ: MutableMapping[str, str]) -> Path:
    """numba's user-wide cache folder on Linux (its ``appdirs.user_cache_dir``)."""
    base = environ.get("XDG_CACHE_HOME") or os.path.join(environ.get("HOME") or os.path.expanduser("~"), ".cache")
    return Path(base) / "numba"


def fallback(environ: MutableMapping[str, str], code: Path = CODE) -> Path | None:
    """The folder for NUMBA_CACHE_DIR where numba could keep the kernels of ``code`` neither beside it nor in the
    user's cache folder; None where it can, where NUMBA_CACHE_DIR already names a folder, off Linux, and where no
    temporary folder can be written either."""
    if environ.get("NUMBA_CACHE_DIR") or not sys.platform.startswith("linux"):
        return None
    if writable(code / "__pycache__") or writable(user_cache(environ)):
        return None
    try:
        return Path(tempfile.gettempdir()) / f"stereo-inspect-numba-{os.getuid()}"
    except OSError:  # no temporary folder can be written either: numba's import error is then said in one line
        return None


def ensure(environ: MutableMapping[str, str] = os.environ, code: Path = CODE) -> str | None:
    """Set NUMBA_CACHE_DIR in ``environ`` to ``fallback``'s folder where there is one, and return the line that says
    so; None where numba has a folder of its own."""
    folder = fallback(environ, code)
    if folder is None:
        return None
    environ["NUMBA_CACHE_DIR"] = str(folder)
    return (f"numba keeps the compiled kernels in {folder}: neither the code's folder ({code.parent}) nor the "
            f"user's cache folder ({user_cache(environ)}) can be written; set NUMBA_CACHE_DIR to keep them elsewhere")
