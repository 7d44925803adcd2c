"""`inspect view` and `inspect run --view`: bad input gets one clear line and exit 2."""
from __future__ import annotations

import socket

from conftest import cli, cli_here, write_recipe
from test_external_plugin import RECIPE

from drivers.plc_sim import free_port


def test_view_without_a_store(tmp_path):
    result = cli_here("view", str(tmp_path / "nothing"))
    assert result.returncode == 2
    assert result.stderr.strip() == f"error: {tmp_path / 'nothing' / 'results.db'}: no results store here (give the recipe's results.path)"


def test_view_on_a_taken_port(tmp_path, plane_sequence, external_plugin_site):
    info = plane_sequence([0.0])
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"]))
    assert cli("run", str(path), "--quiet", env_extra={"PYTHONPATH": str(external_plugin_site)}).returncode == 0
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = cli("view", str(tmp_path / "results"), "--port", str(port))
        assert result.returncode == 2
        assert f"cannot serve on 127.0.0.1:{port}" in result.stderr and "--port" in result.stderr
        assert len(result.stderr.strip().splitlines()) == 1
        # the same for a run: it does not start inspecting without the page it was asked for
        run = cli("run", str(path), "--view", "--port", str(port), env_extra={"PYTHONPATH": str(external_plugin_site)})
        assert run.returncode == 2 and f"cannot serve on 127.0.0.1:{port}" in run.stderr
        assert "parts" not in run.stdout


def test_run_with_view_on_the_network_warns(tmp_path, plane_sequence, external_plugin_site):
    info = plane_sequence([0.0, 6.0])
    port = free_port()
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"]))
    result = cli("run", str(path), "--view", "--host", "0.0.0.0", "--port", str(port),
                 env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert result.returncode == 0, result.stdout + result.stderr
    assert "WITHOUT AUTHENTICATION" in result.stderr
    assert f"operator view: http://0.0.0.0:{port}/" in result.stdout
    assert "parts 2  passed 1  rejected 1" in result.stdout
    with_token = cli("run", str(path), "--view", "--host", "0.0.0.0", "--port", str(port), "--token", "s3cret-token",
                     env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert with_token.returncode == 0 and "WITHOUT AUTHENTICATION" not in with_token.stderr
    assert "?token=s3cret-token" in with_token.stdout
    short = cli("run", str(path), "--view", "--token", "abc", env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert short.returncode == 2 and "--token" in short.stderr
    lonely = cli("run", str(path), "--keep-serving", env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert lonely.returncode == 2 and lonely.stderr.startswith("error: --keep-serving:") and "parts" not in lonely.stdout


def test_view_section_in_the_recipe_is_validated(tmp_path, plane_sequence, external_plugin_site):
    info = plane_sequence([0.0])
    text = RECIPE.format(box=info["box"]) + "view:\n  enabled: true\n  prot: 8081\n"
    path = write_recipe(tmp_path / "r.yaml", text)
    result = cli("validate", str(path), env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert result.returncode == 2 and "view.prot" in result.stderr and "r.yaml:" in result.stderr
    port = free_port()
    good = write_recipe(tmp_path / "good.yaml", RECIPE.format(box=info["box"]) + f"view:\n  enabled: true\n  port: {port}\n")
    run = cli("run", str(good), env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert run.returncode == 0 and f"operator view: http://127.0.0.1:{port}/" in run.stdout


def test_bench_view_measures_the_loop_with_and_without_browsers(tmp_path, plane_sequence, external_plugin_site):
    info = plane_sequence([0.0, 6.0])
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"]))
    result = cli("bench-view", str(path), "--frames", "4", "--browsers", "0,1",
                 env_extra={"PYTHONPATH": str(external_plugin_site)})
    assert result.returncode == 0, result.stdout + result.stderr
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in result.stdout.splitlines() if line.startswith("| ") and "browser" in line and "configuration" not in line}
    assert set(rows) == {"0 browsers", "1 browser", "1 browser + 1 stalled"}
    assert rows["0 browsers"][2:] == ["4", "0", "0"]  # frames, sent, encoded: no browser, no work
    assert int(rows["1 browser"][3]) >= 1 and rows["1 browser"][2] == "4"
    assert rows["1 browser + 1 stalled"][2] == "4"
    assert not (tmp_path / "results").exists()  # benchmark parts stay out of the line's results store
    bad = cli_here("bench-view", str(path), "--browsers", "one")
    assert bad.returncode == 2 and "--browsers" in bad.stderr
    bad = cli_here("bench-view", str(path), "--browsers", "0,-1")
    assert bad.returncode == 2 and "a number of browsers is 0 or more" in bad.stderr
    bad = cli_here("bench-view", str(path), "--browsers", "0,100000000000")
    assert bad.returncode == 2 and "at most 64 browsers" in bad.stderr
