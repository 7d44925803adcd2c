"""What ``inspect run`` shows on a terminal before its first part line."""
from __future__ import annotations

import re

from conftest import cli, write_recipe
from test_recipe_validation import GOOD

from core.commands.inspection import WARMING_UP


def test_the_progress_line_says_warming_up_until_the_first_part(tmp_path, plane_sequence):
    # a machine's first run compiles the kernels for a minute or two before any part: the line says why it waits
    plane_sequence([0.0])
    path = write_recipe(tmp_path / "r.yaml", GOOD.replace("name: t\n", "name: console\n"))
    # without GOOD's master parts, which its 64 px of disparity cannot reach
    run = cli("run", str(path), "--quiet", "--max-frames", "1", "--set", f"results.path={tmp_path / 'res'}",
              "--set", "verify.path=null",
              env_extra={"FORCE_COLOR": "1", "TERM": "xterm", "COLUMNS": "100"})  # rich draws its live line
    assert "parts 1" in run.stdout, run.stdout + run.stderr
    frames = re.split(r"[\r\n]", re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", run.stdout))
    lines = [f.strip() for f in frames if f.strip().startswith("console")]
    waiting = [line for line in lines if line.startswith(f"console: {WARMING_UP}")]
    done = [line for line in lines if re.match(r"console\s+\S+\s+1/1", line)]
    assert waiting and done, lines
    assert lines.index(waiting[-1]) < lines.index(done[0])  # it waits, then it counts the part under its own name
