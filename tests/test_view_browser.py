"""The operator page in a real headless Chromium (Debian's package, driven by Playwright) during a
replayed run of `inspect run --view`, and afterwards over the store with `inspect view`.

Set VIEW_SCREENSHOT=docs/operator-view.png to keep the demo page's screenshot (`make screenshot`).
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import ROOT, write_recipe

from drivers.plc_sim import free_port

sync_api = pytest.importorskip("playwright.sync_api")
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
pytestmark = [
    pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Debian's chromium is not installed (.ci/run installs it)"),
    pytest.mark.slow,
]
# As root and offline: no sandbox, and none of Chromium's background connections to Google.
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync", "--disable-dev-shm-usage"]

# 12 plates; the 6 mm pits (REJECT) arrive from the third plate on, so the filmstrip visibly grows.
PITS = [0.0, 0.0, 6.0, 0.0, 6.0, 0.0, 0.0, 6.0, 0.0, 0.0, 6.0, 0.0]
RECIPE = """\
name: view-e2e
camera:
  plugin: replay
  settings: {{path: seq, rate_fps: 3}}
stereo:
  backend: opencv_sgbm
  working_distance_mm: [300, 600]
detector:
  plugin: fixed_roi
  settings:
    regions:
      - {{name: pit, box: {box}}}
decision:
  rules:
    - {{class: any, quantity: deviation_mm, op: ">", threshold: 1.5, name: deeper than 1.5 mm}}
outputs:
  - plugin: modbus            # nothing listens on this port: every reject becomes an alarm
    settings: {{host: 127.0.0.1, port: {plc_port}, delay_ms: 400, max_late_ms: 100, timeout_ms: 100}}
results:
  path: results
view:
  port: {view_port}
"""


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield b
        b.close()


def _start(args: list[str], env_extra: dict | None = None, cwd: Path | None = None) -> tuple[subprocess.Popen, str]:
    """Start `inspect ...` and return it with the page's URL, read from its output."""
    env = dict(os.environ, PYTHONUNBUFFERED="1", COLUMNS="200", **(env_extra or {}))
    exe = Path(sys.executable).parent / "inspect"
    # Ctrl-C as a terminal gives it: a suite started in the background (`make test &`) hands its children SIGINT
    # ignored, and the page then stayed up until the test's timeout
    proc = subprocess.Popen([str(exe), *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            cwd=cwd, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 120
    seen = []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line and proc.poll() is not None:
            break
        seen.append(line)
        found = re.search(r"(http://127\.0\.0\.1:\d+/\S*)", line)
        if found:
            return proc, found.group(1)
    proc.kill()
    raise AssertionError("the page's address never appeared:\n" + "".join(seen))


def _stop(proc: subprocess.Popen) -> str:
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    return out


def _number(page, selector: str) -> int:
    return int(page.inner_text(selector))


def test_live_page_follows_the_run_and_opens_a_reject(tmp_path, plane_sequence, external_plugin_site, browser):
    info = plane_sequence(PITS)
    view_port = free_port()
    recipe = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], plc_port=free_port(), view_port=view_port))
    proc, url = _start(["run", str(recipe), "--view", "--keep-serving"], {"PYTHONPATH": str(external_plugin_site)})
    try:
        assert url == f"http://127.0.0.1:{view_port}/"
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(url)
        page.wait_for_function("() => ['PASS', 'REJECT', 'ERROR'].includes(document.getElementById('verdict-status').textContent)")
        first = _number(page, "#count-parts")
        page.wait_for_function(f"() => Number(document.getElementById('count-parts').textContent) > {first}")
        # the live frame arrives as an image of the camera's size
        page.wait_for_function("() => Number(document.getElementById('frame').dataset.seq) > 0"
                               " && document.getElementById('frame').naturalWidth === 320")
        # the filmstrip gains rejects while the run goes on
        page.wait_for_selector(".film-item")
        strip = page.locator(".film-item").count()
        page.wait_for_function(f"() => document.querySelectorAll('.film-item').length > {strip}", timeout=30000)
        # the verdict box is coloured by the verdict it shows
        status = page.inner_text("#verdict-status")
        assert status in page.get_attribute("#verdict", "class")
        # an undelivered reject is an alarm on the page until acknowledged
        page.wait_for_selector("#alarms li.alarm", timeout=30000)
        assert "modbus" in page.inner_text("#alarms")
        # click the newest reject: its full image, its defect, and the rule that rejected it
        page.locator(".film-item").first.click()
        page.wait_for_selector("#detail[open]")
        page.wait_for_function("() => document.getElementById('detail-image').naturalWidth === 320")
        assert "rejected by" in page.inner_text("#detail-rule") and "deeper than 1.5 mm" in page.inner_text("#detail-rule")
        defect_row = page.inner_text("#detail-defects tbody tr")
        assert "pit" in defect_row and "REJECT" in defect_row
        assert re.search(r"\+\d+\.\d\d ± \d+\.\d\d", defect_row), defect_row  # the deviation with its uncertainty
        # ... whose parts its tooltip gives, largest first
        parts = page.get_attribute("#detail-defects tbody tr td:nth-child(4)", "title").splitlines()
        assert parts[0] == "uncertainty:" and "placing the surface around the box" in " ".join(parts), parts
        shares = [int(line.split(" %")[0]) for line in parts[1:]]
        assert shares == sorted(shares, reverse=True) and 97 <= sum(shares) <= 103, parts
        page.keyboard.press("Escape")
        # the run ends with every plate counted
        page.wait_for_function("() => document.getElementById('run-state').textContent.includes('finished')", timeout=60000)
        page.wait_for_function(f"() => document.getElementById('count-parts').textContent === '{len(PITS)}'")
        assert _number(page, "#count-rejected") == PITS.count(6.0)
        assert _number(page, "#count-passed") == PITS.count(0.0)
        assert page.locator(".film-item").count() == PITS.count(6.0)
        assert page.text_content("#masters") == "no master parts"  # the recipe names none
        page.screenshot(path=str(tmp_path / "live.png"))
        # acknowledging clears every alarm from the page
        for _ in range(50):
            buttons = page.locator("#alarms button.ack")
            if buttons.count() == 0:
                break
            buttons.first.click()
            page.wait_for_timeout(100)
        page.wait_for_function("() => document.querySelectorAll('#alarms li.alarm').length === 0")
        page.close()
    finally:
        out = _stop(proc)
    assert "parts 12  passed 8  rejected 4" in out, out


def test_review_page_filters_pages_and_exports(tmp_path, plane_sequence, external_plugin_site, browser):
    info = plane_sequence(PITS)
    recipe = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], plc_port=free_port(), view_port=free_port())
                          .replace("rate_fps: 3", "rate_fps: 0"))
    run = subprocess.run([str(Path(sys.executable).parent / "inspect"), "run", str(recipe), "--quiet"],
                         env=dict(os.environ, PYTHONPATH=str(external_plugin_site)), capture_output=True, text=True, timeout=300)
    assert run.returncode == 4, run.stdout + run.stderr  # the alarms of the absent PLC
    port = free_port()
    proc, url = _start(["view", str(tmp_path / "results"), "--port", str(port)])
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(url)
        page.wait_for_function("() => document.getElementById('mode').textContent === 'REVIEW'")
        page.wait_for_function("() => document.querySelectorAll('#parts-table tbody tr').length === 12")
        page.select_option("#filter-verdict", "REJECT")
        page.wait_for_function("() => document.querySelectorAll('#parts-table tbody tr').length === 4")
        assert all(v == "REJECT" for v in page.locator("#parts-table tbody td:nth-child(4)").all_inner_texts())
        assert "verdict=REJECT" in page.get_attribute("#export-csv", "href")
        with page.expect_download() as download:
            page.click("#export-csv")
        lines = Path(download.value.path()).read_text().splitlines()
        assert lines[0].startswith("run_id,part_id") and len(lines) == 1 + 4
        page.select_option("#filter-verdict", "")
        page.select_option("#filter-class", "pit")
        page.wait_for_function("() => document.getElementById('page-info').textContent.includes('12 parts')")
        page.locator("#parts-table tbody tr").nth(1).click()
        page.wait_for_selector("#detail[open]")
        assert page.inner_text("#detail-title").startswith("R1-")
        # the store damaged while the page is up: its reason, where it said "no connection to the inspection PC"
        for path in (tmp_path / "results").glob("results.db*"):
            path.unlink()
        (tmp_path / "results" / "results.db").write_bytes(b"not a database" * 100)
        page.wait_for_function("() => document.getElementById('connection').textContent.includes("
                               "'the results store cannot be read (file is not a database)')")
        page.close()
    finally:
        _stop(proc)


@pytest.mark.skipif(not (ROOT / "models" / "yolov8n-neu-det.pt").exists(), reason="committed weights missing")
def test_demo_recipe_page(tmp_path, browser):
    """The product's own demo (`recipes/steel_plate.yaml`) behind the page; its screenshot is the one in docs/."""
    port = free_port()
    proc, url = _start(["run", str(ROOT / "recipes" / "steel_plate.yaml"), "--plc-sim", "--view", "--port", str(port),
                        "--keep-serving", "--set", f"results.path={tmp_path / 'results'}",
                        "--set", f"outputs.1.settings.file={tmp_path / 'rejects.log'}"])
    try:
        page = browser.new_page(viewport={"width": 1280, "height": 860})
        page.goto(url)
        page.wait_for_function("() => document.getElementById('run-state').textContent.includes('finished')", timeout=120000)
        page.wait_for_function("() => document.getElementById('frame').naturalWidth === 672")
        assert _number(page, "#count-parts") == 10
        masters = page.locator("#masters")  # checked before the first plate, its tally on hover
        assert masters.text_content() == "master parts ✓" and "3 of 3 defective ones rejected" in masters.get_attribute("title")
        if page.locator(".film-item").count():
            page.wait_for_function("() => [...document.querySelectorAll('.film-item img')].every(i => i.naturalWidth === 160)")
        page.screenshot(path=os.environ.get("VIEW_SCREENSHOT") or str(tmp_path / "demo.png"), full_page=True)
        page.close()
    finally:
        out = _stop(proc)
    assert "parts 10" in out, out
