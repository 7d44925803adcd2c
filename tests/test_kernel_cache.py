"""A folder numba can keep the compiled kernels in where the code's folder and the user's cache cannot be written
(core/kernel_cache.py)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from core import kernel_cache

ROOT = Path(__file__).resolve().parents[1]
NOWHERE = Path("/proc/stereo-inspect-nowhere")  # a folder no user can make


class TestWritable:
    def test_a_folder_that_can_be_made_is(self, tmp_path):
        assert kernel_cache.writable(tmp_path / "new" / "folder")
        assert (tmp_path / "new" / "folder").is_dir()

    def test_a_folder_that_cannot_be_made_is_not(self):
        assert not kernel_cache.writable(NOWHERE / "cache")


class TestFallback:
    def test_none_where_the_code_s_folder_can_be_written(self, tmp_path):
        assert kernel_cache.fallback({"XDG_CACHE_HOME": str(NOWHERE)}, tmp_path / "code") is None

    def test_none_where_the_user_s_cache_can_be_written(self, tmp_path):
        assert kernel_cache.fallback({"XDG_CACHE_HOME": str(tmp_path)}, NOWHERE / "code") is None
        assert (tmp_path / "numba").is_dir()
        assert kernel_cache.fallback({"HOME": str(tmp_path)}, NOWHERE / "code") is None
        assert (tmp_path / ".cache" / "numba").is_dir()

    def test_a_temporary_folder_of_this_user_s_where_neither_can(self):
        found = kernel_cache.fallback({"XDG_CACHE_HOME": str(NOWHERE)}, NOWHERE / "code")
        assert found == Path(tempfile.gettempdir()) / f"stereo-inspect-numba-{os.getuid()}"

    def test_none_where_numba_cache_dir_names_one_already(self):
        assert kernel_cache.fallback({"NUMBA_CACHE_DIR": "/somewhere", "XDG_CACHE_HOME": str(NOWHERE)},
                                     NOWHERE / "code") is None


class TestEnsure:
    def test_it_sets_numba_cache_dir_and_says_where_and_why(self):
        environ = {"XDG_CACHE_HOME": str(NOWHERE)}
        said = kernel_cache.ensure(environ, NOWHERE / "code")
        assert environ["NUMBA_CACHE_DIR"] == str(Path(tempfile.gettempdir()) / f"stereo-inspect-numba-{os.getuid()}")
        assert environ["NUMBA_CACHE_DIR"] in said and str(NOWHERE / "numba") in said and "NUMBA_CACHE_DIR" in said

    def test_it_leaves_the_environment_alone_where_numba_has_a_folder(self, tmp_path):
        environ = {"XDG_CACHE_HOME": str(tmp_path)}
        assert kernel_cache.ensure(environ, NOWHERE / "code") is None
        assert environ == {"XDG_CACHE_HOME": str(tmp_path)}


def read_only(*mounts: str, script: str, env: dict[str, str]) -> subprocess.CompletedProcess:
    """``script`` (bash) in a mount namespace of its own where ``mounts`` are bound read-only over themselves."""
    binds = " && ".join(f"mount --bind -o ro {m} {m}" for m in mounts)
    return subprocess.run(["unshare", "-m", "bash", "-c", f"{binds} && cd {ROOT} && {script}"], capture_output=True,
                          text=True, timeout=120, env={**os.environ, **env})


def can_mount_read_only() -> bool:
    if shutil.which("unshare") is None or os.geteuid() != 0:
        return False
    return subprocess.run(["unshare", "-m", "bash", "-c", f"mount --bind -o ro {ROOT} {ROOT}"],
                          capture_output=True).returncode == 0


needs_mounts = pytest.mark.skipif(not can_mount_read_only(),
                                  reason="needs root and `unshare -m` to mount the code's folder read-only")
NO_HOME = {"HOME": str(NOWHERE), "XDG_CACHE_HOME": str(NOWHERE)}


@needs_mounts
class TestOnAReadOnlyInstall:
    def test_numba_imports_a_kernel_s_module_once_ensured_and_failed_without(self):
        importing = f"{sys.executable} -c 'from core import kernel_cache; {{}}; import core.surface_fit_numba'"
        failed = read_only(str(ROOT), script=importing.format("pass"), env=NO_HOME)
        assert failed.returncode != 0 and "cannot cache function" in failed.stderr
        ensured = read_only(str(ROOT), script=importing.format("print(kernel_cache.ensure())"), env=NO_HOME)
        assert ensured.returncode == 0, ensured.stderr
        assert "numba keeps the compiled kernels in" in ensured.stdout

    def test_inspect_says_where_it_keeps_them(self):
        result = read_only(str(ROOT), script=f"{sys.executable} -c 'from core.cli import main; main()' --version",
                           env=NO_HOME)
        assert result.returncode == 0, result.stderr
        assert "numba keeps the compiled kernels in" in result.stderr

    def test_nowhere_to_keep_them_is_one_line_and_exit_2(self):
        script = f"{sys.executable} -c 'from core.cli import main; main()' run recipes/steel_plate.yaml --max-frames 1"
        temporary = [d for d in (tempfile.gettempdir(), "/tmp", "/var/tmp", "/usr/tmp") if os.path.isdir(d)]
        result = read_only(str(ROOT), *dict.fromkeys(temporary), script=script, env={**NO_HOME, "TMPDIR": str(NOWHERE)})
        assert result.returncode == 2, result.stderr
        assert result.stderr.strip().splitlines()[-1].startswith("Error: numba can keep the compiled kernels nowhere")
        assert "Traceback" not in result.stderr
