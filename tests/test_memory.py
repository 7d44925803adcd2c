"""core.memory: freed blocks stay in the process (checked in fresh interpreters, since the setting is
process-wide)."""
from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

SCRIPT = """
import sys
import numpy as np
from core.memory import keep_freed_memory

def rss():
    return int(open('/proc/self/statm').read().split()[1]) * 4096

if sys.argv[1] == 'keep':
    assert keep_freed_memory() and keep_freed_memory()
if sys.argv[1] == 'off':
    assert not keep_freed_memory()
block = np.ones(64 * 2**20, np.uint8)
held = rss()
del block
print((held - rss()) // 2**20)
"""


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="the switches are glibc's")
def test_a_freed_block_stays_in_the_process_only_when_asked():
    def returned_mb(mode, **env):
        out = subprocess.run([sys.executable, "-c", SCRIPT, mode], capture_output=True, text=True, check=True,
                             env={**os.environ, **env})
        return int(out.stdout)

    assert returned_mb("default") >= 60   # glibc unmaps a 64 MB block on free
    assert returned_mb("keep") <= 4       # kept for the next frame's volumes
    assert returned_mb("off", STEREO_INSPECT_KEEP_MEMORY="0") >= 60  # the opt-out
