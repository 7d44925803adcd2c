"""Whether a file could be written where a recipe says, found out without writing it.

A recipe is checked before the run opens any hardware; a file its run would write (the results store, a
log of reject commands) that cannot be written there must be said then, naming the recipe's key, not at
the first reject as an alarm per part.
"""
from __future__ import annotations

import os
from pathlib import Path


def unwritable(path: Path) -> str | None:
    """Why a file at ``path`` could not be created or appended to (a folder in its way or in its place, a
    folder that is not writable, a name the file system refuses), in words; None where it could. Creates
    nothing."""
    path = Path(path)
    try:
        if path.is_dir():
            return f"{path} is a folder"
        if path.exists():
            return None if os.access(path, os.W_OK) else f"{path} is not writable"
        existing = path.parent
        while not existing.exists():
            existing = existing.parent
        if not existing.is_dir():
            return f"{existing} is a file, not a folder"
        if not os.access(existing, os.W_OK | os.X_OK):
            return f"{existing} is not writable"
        limit = os.statvfs(existing).f_namemax
        too_long = [part for part in path.relative_to(existing).parts if len(os.fsencode(part)) > limit]
        if too_long:
            return f"the name {too_long[0][:40]}... is longer than the file system's {limit} bytes"
    except OSError as exc:
        return f"{path}: {exc.strerror or exc}"
    return None
