"""Keep freed memory in the process instead of handing it back to the system after every frame.

Each frame the matcher allocates and frees volumes of tens of MB. glibc serves blocks that large with
fresh ``mmap`` pages and unmaps them on free, so every frame pays a page fault per 4 KiB again: on the
development machine that was 17 % of torch_sgm's time on a WVGA frame (docs/research-log.md). PyTorch's
CPU tuning guide recommends jemalloc or tcmalloc through LD_PRELOAD for the same reason; this does the
equivalent from inside the process, with glibc's own switches, so ``inspect`` needs no launcher.
Resident memory then stays at its peak instead of falling between frames, which for a process that
inspects frame after frame is where it would return anyway.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os

M_TRIM_THRESHOLD = -1  # from glibc's malloc.h
M_MMAP_MAX = -4


@functools.lru_cache(maxsize=1)
def keep_freed_memory() -> bool:
    """Serve large blocks from the heap and never trim it; True where that took effect (glibc), False
    elsewhere (musl, macOS, Windows), where the allocator is left as it is, and where the environment
    sets ``STEREO_INSPECT_KEEP_MEMORY=0`` (to compare, or to share a small machine)."""
    if os.environ.get("STEREO_INSPECT_KEEP_MEMORY", "1").strip() == "0":
        return False
    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # mallopt returns 1 on success; both or neither
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, 2**31 - 1))
