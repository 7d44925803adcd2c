"""``drivers.file_writes``: a file that cannot be written is named, and what the failed write left is gone."""
from __future__ import annotations

import errno
from pathlib import Path

import pytest

from drivers.file_writes import write_bytes, write_text


class TestWriteBytes:
    def test_writes_the_whole_file(self, tmp_path):
        write_bytes(tmp_path / "a.bin", b"\x00\x01")
        write_text(tmp_path / "b.txt", "ü\n")
        assert (tmp_path / "a.bin").read_bytes() == b"\x00\x01" and (tmp_path / "b.txt").read_text("utf-8") == "ü\n"

    @pytest.mark.skipif(not Path("/dev/full").exists(), reason="no /dev/full (a device that is always full) here")
    def test_a_full_disk_is_said_with_the_file(self):
        with pytest.raises(OSError, match=r"^/dev/full: could not be written \(No space left on device\)$"):
            write_text(Path("/dev/full"), "x" * 10_000)
        assert Path("/dev/full").exists()  # a device is never removed

    def test_a_write_cut_short_leaves_nothing(self, tmp_path, monkeypatch):
        def half_then_full(self, data):
            with open(self, "wb") as f:
                f.write(data[: len(data) // 2])
            raise OSError(errno.ENOSPC, "No space left on device")

        monkeypatch.setattr(Path, "write_bytes", half_then_full)
        with pytest.raises(OSError, match=r"labels\.json: could not be written \(No space left on device\)"):
            write_text(tmp_path / "labels.json", '{"defects": []}')
        assert not (tmp_path / "labels.json").exists()

    def test_a_folder_that_is_a_file_is_named(self, tmp_path):
        (tmp_path / "out").write_text("")
        with pytest.raises(OSError, match=r"out/x\.json: could not be written \(Not a directory\)"):
            write_text(tmp_path / "out" / "x.json", "{}")
