"""Command-line values a command cannot use are refused in one line before its work: a folder for its files
that cannot be made (an evaluation of minutes would otherwise end in a traceback), a count below one."""
from __future__ import annotations

import re

import pytest
from click.testing import CliRunner

from conftest import cli_here

from core.cli import _build

SEQUENCE = "sim_fixtures/plates_textured"
PAIR = ("sim_fixtures/steel_plate/left/000000.jpg", "sim_fixtures/steel_plate/right/000000.jpg")


@pytest.fixture
def blocked(tmp_path):
    """A path under a plain file: no folder can be made there."""
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    return blocker / "out"


@pytest.mark.parametrize("args, option", [
    (["eval", "depth", SEQUENCE, "--out", "{out}"], "--out"),
    (["bench", "--backends", "none", "--out", "{out}"], "--out"),
    (["eval", "stereo", "--middlebury", "nowhere", "--out", "{out}"], "--out"),
    (["stereo", *PAIR, "--max-disp", "64", "--out", "{out}/d.pfm"], "--out"),
    (["report", "results", "--csv", "{out}/parts.csv"], "--csv"),
    (["eval", "detector", "--data", "nowhere", "--weights", "nowhere.pt", "--out", "{out}"], "--out"),
])
def test_an_output_folder_that_cannot_be_made_is_refused_first(blocked, args, option):
    result = CliRunner().invoke(_build(), [a.replace("{out}", str(blocked)) for a in args])
    assert result.exit_code == 2, result.output
    assert f"Invalid value for '{option}'" in result.output and "cannot create the folder" in result.output


def test_sim_generate_says_it_cannot_make_its_folder(blocked):
    result = CliRunner().invoke(_build(), ["sim", "generate", str(blocked), "--frames", "1", "--synthetic-defects"])
    assert result.exit_code == 2
    assert f"error: {blocked}: cannot create the folder" in result.output


@pytest.mark.parametrize("args, option", [
    (["run", "recipes/steel_plate.yaml", "--max-frames", "0"], "--max-frames"),  # it inspected one part
    (["stereo", *PAIR, "--max-disp", "64", "--threads", "0"], "--threads"),  # it ran
    (["plc-sim", "--baudrate", "0"], "--baudrate"),
])
def test_counts_below_one_are_usage_errors_not_something_else(args, option):
    result = CliRunner().invoke(_build(), args)
    assert result.exit_code == 2 and f"Invalid value for '{option}'" in result.output, result.output


@pytest.mark.parametrize("command", [("report",), ("eval", "depth"), ("eval", "stereo", "--middlebury"), ("view",)])
def test_a_path_the_file_system_refuses_is_one_line_not_a_traceback(command):
    """A name longer than the file system takes raises OSError at the first look, in whichever command."""
    result = cli_here(*command, "x" * 300)
    assert result.returncode == 2
    assert re.fullmatch(r"error: x{300}(/results.db)?: File name too long\n", result.stderr), result.stderr
