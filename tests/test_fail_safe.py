"""The fail-safe line: nothing passes that the system could not vouch for, no reject vanishes without an
alarm, no code runs from a model file. One test (or a few) per way it used to fail, against real parts:
a real pymodbus server, real files, real signals, a real subprocess killed with SIGKILL."""
from __future__ import annotations

import json
import os
import re
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest
from conftest import ROOT, cli, cli_here

from core.contracts import PluginSpec
from core.engine import frame_age_limit_s, inspect_frame
from core.hookspecs import hookimpl
from core.recipe import RecipeError, load_recipe
from core.registry import Registry, make_manager
from core.types import FrameError, Status, StereoFrame
from drivers import plc_sim
from drivers.zed_uvc import capture_time
from plugins.replay_camera import ReplayCamera, ReplaySettings

DEMO = ROOT / "recipes" / "steel_plate.yaml"
FIXTURE = ROOT / "sim_fixtures" / "steel_plate"
WEIGHTS = ROOT / "models" / "yolov8n-neu-det.pt"


def _one_line_error(result, *needles):
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), result.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


# -- 1. no code from a model file ---------------------------------------------------------------------

def _booby_trapped_weights(path: Path, marker: Path) -> Path:
    import torch

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {marker}",))

    torch.save({"model": Payload()}, path)
    return path


def test_a_checkpoint_that_would_run_code_is_refused_and_never_run(tmp_path):
    marker = tmp_path / "pwned"
    weights = _booby_trapped_weights(tmp_path / "evil.pt", marker)
    result = cli("validate", str(DEMO), "--set", f"detector.weights={weights}")
    _one_line_error(result, "evil.pt", "refused", "posix.system", "trust_pickle")
    result = cli("run", str(DEMO), "--set", f"detector.weights={weights}", "--set", f"results.path={tmp_path / 'r'}")
    assert result.returncode == 2 and "refused" in result.stderr
    assert not marker.exists(), "the checkpoint's pickle ran"
    # the opt-in reads it in full, which is what runs it: the setting means what it says
    from plugins.yolov8.detector import read_checkpoint

    with pytest.raises(ValueError):
        read_checkpoint(weights, trust_pickle=True)
    assert marker.exists()


@pytest.mark.parametrize("content, says", [(b"", "this one is empty"), (b"<html>", "this one starts with b'<htm'")])
def test_weights_that_are_no_torch_file_are_said_to_be_so(tmp_path, content, says):
    # a download that saved an error page, a file cut to nothing: the loader's own words were "KeyError: 60"
    weights = tmp_path / "model.pt"
    weights.write_bytes(content)
    _one_line_error(cli_here("validate", str(DEMO), "--set", f"detector.weights={weights}"), "detector.weights",
                    f"{weights}: not a YOLO checkpoint: a torch file is a zip archive or a pickle, and {says}")
    _one_line_error(cli_here("eval", "detector-frames", str(ROOT / "sim_fixtures" / "steel_plate"), "--weights",
                        str(weights)), f"{weights}: not a YOLO checkpoint")


def test_weights_holding_nan_are_refused_not_run_as_a_detector_that_finds_nothing(tmp_path):
    # a diverged training's or a damaged average's model: NMS kept none of its NaN-scored boxes, and every part of
    # the demo passed, 7 of them defective
    import torch

    checkpoint = torch.load(WEIGHTS, weights_only=False)
    model = checkpoint.get("ema") or checkpoint["model"]
    next(model.parameters()).data.fill_(float("nan"))
    weights = tmp_path / "diverged.pt"
    torch.save(checkpoint, weights)
    says = "1 of the model's weight tensors holds NaN or infinite values (the first model.0.conv.weight)"
    _one_line_error(cli_here("validate", str(DEMO), "--set", f"detector.weights={weights}"), "detector.weights", says)
    _one_line_error(cli_here("train", "average", str(WEIGHTS), str(weights), "--out", str(tmp_path / "soup.pt")), says)
    assert not (tmp_path / "soup.pt").exists()
    from plugins.yolov8.detector import YoloDetector, YoloSettings

    with pytest.raises(ValueError, match=re.escape(says)):
        YoloDetector(YoloSettings(weights=str(weights)))


def test_the_weights_can_be_pinned_and_every_run_records_what_it_ran(tmp_path):
    bad = cli_here("validate", str(DEMO), "--set", "detector.sha256=" + "ab" * 32)
    _one_line_error(bad, "detector.sha256", "yolov8n-neu-det.pt has SHA-256", "not the pinned")
    from core.recipe.loader import file_sha256

    digest = file_sha256(WEIGHTS)
    assert cli_here("validate", str(DEMO), "--set", f"detector.sha256={digest}").returncode == 0
    results = tmp_path / "results"
    out = cli("run", str(DEMO), "--quiet", "--max-frames", "2", "--set", f"detector.sha256={digest}",
              "--set", f"results.path={results}", "--set", f"outputs=[{{plugin: log, settings: {{file: {tmp_path}/log}}}}]")
    assert out.returncode in (0, 3), out.stderr
    db = sqlite3.connect(results / "results.db")
    recipe_sha, models = db.execute("SELECT recipe_sha256, models FROM runs").fetchone()
    assert recipe_sha == file_sha256(DEMO) and json.loads(models) == {str(WEIGHTS): digest}
    assert db.execute("SELECT COUNT(*) FROM parts WHERE run_id = 1").fetchone()[0] == 2


# -- 2. a rule naming a class the detector does not know -----------------------------------------------

def test_a_misspelled_class_in_a_rule_is_an_error_with_the_known_classes():
    result = cli_here("validate", str(DEMO), "--set", "decision.rules.0.class=scrach")
    _one_line_error(result, "steel_plate.yaml", "decision.rules.0.class", "unknown class 'scrach'",
                    "did you mean 'scratches'?", "crazing, inclusion, patches, pitted_surface, rolled-in_scale, scratches")
    assert cli_here("run", str(DEMO), "--set", "decision.rules.0.class=scrach").returncode == 2
    digits = cli_here("validate", str(DEMO), "--set", "detector.sha256=" + "1" * 64)
    _one_line_error(digits, "detector.sha256", "in quotes")


# -- 3. frames that are whole or ERROR -------------------------------------------------------------------

@pytest.mark.parametrize("suffix", ["jpg", "png"])
def test_a_truncated_image_is_a_frame_error_naming_the_file(tmp_path, suffix):
    import cv2

    copy = tmp_path / "seq"
    shutil.copytree(FIXTURE, copy)
    if suffix == "png":  # the same frame saved lossless
        for eye in ("left", "right"):
            image = cv2.imread(str(copy / eye / "000002.jpg"))
            (copy / eye / "000002.jpg").unlink()
            cv2.imwrite(str(copy / eye / "000002.png"), image)
    victim = copy / "left" / f"000002.{suffix}"
    data = victim.read_bytes()
    victim.write_bytes(data[: int(0.4 * len(data))])  # the copy stopped at 40 %
    frames = list(ReplayCamera(ReplaySettings(path=str(copy), max_frames=4)).frames())
    assert [type(f) for f in frames] == [StereoFrame, StereoFrame, FrameError, StereoFrame]
    assert str(victim) in frames[2].message and "not whole" in frames[2].message


def test_a_truncated_frame_is_never_a_pass(tmp_path):
    copy = tmp_path / "seq"
    shutil.copytree(FIXTURE, copy)
    victim = copy / "left" / "000002.jpg"
    victim.write_bytes(victim.read_bytes()[: int(0.4 * victim.stat().st_size)])
    results = tmp_path / "results"
    out = cli("run", str(DEMO), "--set", f"camera.settings.path={copy}", "--set", "camera.settings.max_frames=3",
              "--set", f"results.path={results}", "--set", f"outputs=[{{plugin: log, settings: {{file: {tmp_path}/log}}}}]")
    assert out.returncode == 3, out.stdout + out.stderr  # parts that could not be inspected
    verdict, error = sqlite3.connect(results / "results.db").execute(
        "SELECT verdict, error FROM parts WHERE frame_id = '000002'").fetchone()
    assert verdict == "ERROR" and "000002.jpg" in error and "not whole" in error
    assert "Premature end of JPEG" not in out.stderr  # decided from the file, not from a decoder's warning


# -- 5, 6, 7, 10: the real process, the real PLC ---------------------------------------------------------

def _run_args(results: Path, port: int, *extra: str) -> list[str]:
    return [str(DEMO), "--quiet", "--set", f"results.path={results}", "--set", f"outputs.0.settings.port={port}",
            "--set", f"outputs.1.settings.file={results / 'rejects.log'}", "--set", "camera.settings.loop=true",
            "--set", "camera.settings.rate_fps=8", "--set", "stereo.backend=opencv_sgbm",
            "--set", "outputs.0.settings.conveyor_speed_mm_s=300", *extra]  # 2 s from camera to actuator


def _spawn(args: list[str]) -> subprocess.Popen:
    exe = Path(sys.executable).parent / "inspect"
    return subprocess.Popen([str(exe), "run", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _assert_each_reject_delivered_or_alarmed(db: sqlite3.Connection, part_ids: list[str] | None = None) -> None:
    """Each of ``part_ids`` (default: every part not passed) reached the PLC, or the operator heard why not."""
    if part_ids is None:
        part_ids = [r[0] for r in db.execute("SELECT part_id FROM parts WHERE verdict != 'PASS'")]
    for part_id in part_ids:
        outcomes = {r[0] for r in db.execute(
            "SELECT outcome FROM output_events WHERE part_id = ? AND output = 'modbus' AND command LIKE '%(pulse%'",
            (part_id,))}
        assert outcomes & {"delivered", "alarm"}, part_id


def _wait_for_parts(results: Path, count: int, timeout: float = 90.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with sqlite3.connect(results / "results.db", timeout=1) as db:
                if db.execute("SELECT COUNT(*) FROM parts").fetchone()[0] >= count:
                    return
        except sqlite3.Error:
            pass
        time.sleep(0.2)
    raise AssertionError(f"no {count} parts in {timeout} s")


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_sigterm_and_sighup_stop_the_run_as_ctrl_c_does(tmp_path, signum):
    """What `systemctl stop` does: the rejects still on their way to the actuator are delivered (or alarmed),
    the ready coil drops, the run row is closed."""
    port = plc_sim.free_port()
    results = tmp_path / "results"
    with plc_sim.serve_in_thread("127.0.0.1", port, on_change=None) as sim:
        proc = _spawn(_run_args(results, port))
        _wait_for_parts(results, 6)
        assert sim.coil(1) == 1  # the ready coil, while it runs
        proc.send_signal(signum)
        out, err = proc.communicate(timeout=60)
        assert proc.returncode == 128 + signum, out + err
        assert f"stopped by {signal.Signals(signum).name}" in out
        assert sim.coil(1) == 0 and sim.coil(0) == 0
    db = sqlite3.connect(results / "results.db")
    status, finished, parts = db.execute("SELECT status, finished, parts FROM runs").fetchone()
    assert status == "finished" and finished is not None
    assert parts == db.execute("SELECT COUNT(*) FROM parts").fetchone()[0]
    rejected = [r[0] for r in db.execute("SELECT part_id FROM parts WHERE verdict != 'PASS'")]
    assert rejected, "the sequence should have had rejects queued"
    _assert_each_reject_delivered_or_alarmed(db, rejected)
    rising = len([w for w in sim.writes if w.table == "coil" and w.address == 0 and w.value == 1])
    delivered = db.execute("SELECT COUNT(*) FROM output_events WHERE output = 'modbus' AND command LIKE '%(pulse%' "
                           "AND outcome = 'delivered'").fetchone()[0]
    assert rising == delivered


def test_ctrl_c_again_while_rejects_are_on_their_way_alarms_them_and_finishes_the_run(tmp_path):
    """A second Ctrl-C during the wait for the plates still on their way ended the process ("Aborted!") with
    those rejects unsent, no alarm, and the run left open."""
    port = plc_sim.free_port()
    results = tmp_path / "results"
    exe = Path(sys.executable).parent / "inspect"
    with plc_sim.serve_in_thread("127.0.0.1", port, on_change=None):
        # a terminal's Ctrl-C: SIGINT with Python's own handler (a background child would inherit it ignored)
        proc = subprocess.Popen([str(exe), "run", *_run_args(results, port)], stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        _wait_for_parts(results, 6)
        proc.send_signal(signal.SIGINT)
        time.sleep(0.5)  # the run is now waiting for the rejects due up to 2 s after their capture
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Aborted" not in out + err, out + err
    db = sqlite3.connect(results / "results.db")
    assert db.execute("SELECT status FROM runs").fetchone()[0] == "finished"
    abandoned = db.execute("SELECT COUNT(*) FROM alarms WHERE message LIKE '%stopped again (Ctrl-C) while its plate "
                           "was on its way%'").fetchone()[0]
    assert abandoned >= 1, out
    _assert_each_reject_delivered_or_alarmed(db)


def test_a_console_whose_reader_went_away_stops_the_run_as_a_closed_terminal_does(tmp_path):
    """`inspect run | head`: rich raised SystemExit from inside the run loop when the pipe broke, which skipped
    finalising the run (left "running" in the store, no exit code) and recording what was still to come."""
    port = plc_sim.free_port()
    results = tmp_path / "results"
    exe = Path(sys.executable).parent / "inspect"
    args = [a for a in _run_args(results, port) if a != "--quiet"]  # a line per part, to the pipe
    with plc_sim.serve_in_thread("127.0.0.1", port, on_change=None):
        proc = subprocess.Popen([str(exe), "run", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        lines = [proc.stdout.readline() for _ in range(4)]
        proc.stdout.close()  # the reader goes away, as `head -4` does
        err = proc.stderr.read()
        proc.wait(timeout=60)
    assert lines[0].startswith("master parts ") and all(line.startswith("R1-") for line in lines[1:]), lines
    assert proc.returncode == 128 + signal.SIGPIPE and "Traceback" not in err, err
    db = sqlite3.connect(results / "results.db")
    assert db.execute("SELECT status, exit_code FROM runs").fetchone() == ("finished", 128 + signal.SIGPIPE)
    _assert_each_reject_delivered_or_alarmed(db)


def test_a_plc_unreachable_all_run_is_an_alarm_even_without_rejects(tmp_path):
    port = plc_sim.free_port()  # nothing listens there
    results = tmp_path / "results"
    # a detector that finds nothing (and no master parts, which would keep such a line from starting)
    out = cli("run", *_run_args(results, port, "--max-frames", "3", "--set", "detector.confidence=1.0",
                                "--set", "camera.settings.loop=false", "--set", "verify.path=null"))
    assert out.returncode == 4, out.stdout + out.stderr
    assert f"the PLC at 127.0.0.1:{port} cannot be reached" in out.stdout
    # the hint names the real cause, and offers the simulator only where it was not given
    assert f"the PLC at 127.0.0.1:{port} did not answer" in out.stdout and "pass --plc-sim" in out.stdout
    assert "decided after their reject was due" not in out.stdout
    db = sqlite3.connect(results / "results.db")
    assert db.execute("SELECT COUNT(*) FROM parts WHERE verdict = 'PASS'").fetchone()[0] == 3
    assert db.execute("SELECT COUNT(*) FROM alarms WHERE part_id IS NULL").fetchone()[0] == 1


def test_the_exit_4_hint_says_when_inspection_was_the_late_one(tmp_path):
    """A reject due 10 ms after capture cannot be on time however fast the PLC: the hint says so, and does
    not send the user looking for a PLC that answered."""
    port = plc_sim.free_port()
    results = tmp_path / "results"
    with plc_sim.serve_in_thread("127.0.0.1", port, on_change=None):
        out = cli("run", str(DEMO), "--plc-sim", "--quiet", "--set", f"results.path={results}",
                  "--set", f"outputs.0.settings.port={port}", "--set", f"outputs.1.settings.file={results}/log",
                  "--set", "stereo.backend=opencv_sgbm", "--set", "outputs.0.settings.actuator_distance_mm=null",
                  "--set", "outputs.0.settings.conveyor_speed_mm_s=null", "--set", "outputs.0.settings.delay_ms=10",
                  # 1 ms of grace: a reject due 10 ms after capture is late on any machine, however fast
                  "--set", "outputs.0.settings.max_late_ms=1",
                  "--set", "camera.settings.rate_fps=0", "--set", "camera.settings.max_frames=4",
                  "--set", "camera.max_frame_age_ms=5000")
    assert out.returncode == 4, out.stdout + out.stderr
    assert "decided after their reject was due" in out.stdout
    assert "did not answer" not in out.stdout and "pass --plc-sim" not in out.stdout


def test_after_a_crash_the_next_run_says_which_rejects_may_not_have_fired(tmp_path):
    """SIGKILL (or a power cut) mid-run: nothing can be finalised then, so the next start finds the run,
    marks it crashed with its true counts and raises an alarm for each reject no output confirmed."""
    port = plc_sim.free_port()
    results = tmp_path / "results"
    with plc_sim.serve_in_thread("127.0.0.1", port, on_change=None):
        proc = _spawn(_run_args(results, port))
        _wait_for_parts(results, 7)  # rejects decided; with 2 s to the actuator, some not yet fired
        proc.kill()
        proc.wait(10)
        db = sqlite3.connect(results / "results.db")
        crashed_parts = db.execute("SELECT COUNT(*) FROM parts WHERE run_id = 1").fetchone()[0]
        # the rejects the PLC had not confirmed (the log output confirms as it writes)
        unconfirmed = [r[0] for r in db.execute(
            "SELECT part_id FROM parts p WHERE run_id = 1 AND verdict != 'PASS' AND NOT EXISTS (SELECT 1 FROM "
            "output_events e WHERE e.part_id = p.part_id AND e.outcome = 'delivered' AND e.output = 'modbus')")]
        db.close()
        assert unconfirmed, "the kill should have caught rejects on their way"
        out = cli("run", *_run_args(results, port, "--max-frames", "2", "--set", "camera.settings.loop=false"))
    assert out.returncode == 4, out.stdout + out.stderr
    for part_id in unconfirmed:
        assert f"part {part_id} was " in out.stdout and "may not have fired" in out.stdout
    assert "run 1 ended without finishing" in out.stdout and "an earlier run ended without finishing" in out.stdout
    db = sqlite3.connect(results / "results.db")
    status, parts = db.execute("SELECT status, parts FROM runs WHERE id = 1").fetchone()
    assert status == "crashed" and parts == crashed_parts
    stored = {r[0] for r in db.execute("SELECT part_id FROM alarms WHERE run_id = 2 AND part_id IS NOT NULL")}
    assert set(unconfirmed) <= stored
    report = cli_here("report", str(results))
    assert "run 1 crashed" in report.stdout and f"{len(unconfirmed)} of them rejected without a confirmed output" in report.stdout
    assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"


# -- 8. outputs that cannot deliver ------------------------------------------------------------------------

def test_an_output_without_a_delay_or_with_one_shorter_than_a_frame_is_an_error():
    result = cli_here("validate", str(DEMO), "--set", "outputs.0.settings.actuator_distance_mm=null",
                      "--set", "outputs.0.settings.conveyor_speed_mm_s=null")
    _one_line_error(result, "outputs.0.settings", "give the time from the camera to the actuator")
    result = cli_here("validate", str(DEMO), "--set", "outputs.0.settings.conveyor_speed_mm_s=6000")  # 100 ms at 4 fps
    _one_line_error(result, "outputs.0.settings.actuator_distance_mm", "100 ms after a part's capture",
                    "frame period (250 ms at 4 fps)", "set delay_ms to at least 250")


class _AirJetOutputs:
    """A third-party output that states its delay under its own key."""

    @staticmethod
    @hookimpl
    def stereo_inspect_outputs():
        return [PluginSpec(name="air_jet", kind="output", factory=lambda settings, ctx: None,
                           actuator_delay=lambda settings, ctx: settings["jet_after_s"])]


def test_a_third_party_output_that_states_its_delay_is_held_to_the_same_checks():
    registry = Registry(make_manager((_AirJetOutputs,)))
    jet = ["outputs=[{plugin: air_jet, settings: {jet_after_s: 0.1}}]"]
    with pytest.raises(RecipeError, match=r"outputs\.0\.settings: the command is due 100 ms .* frame period \(250 ms"):
        load_recipe(DEMO, jet, registry=registry)
    slow = load_recipe(DEMO, ["outputs=[{plugin: air_jet, settings: {jet_after_s: 0.8}}]"], registry=registry)
    assert frame_age_limit_s(slow, registry) == pytest.approx(0.8)


# -- 9. time: frames carry their capture time; a frame too old is an ERROR ----------------------------------

def test_the_replay_camera_stamps_the_schedule_it_plays_even_when_read_late():
    camera = ReplayCamera(ReplaySettings(path=str(FIXTURE), rate_fps=20, max_frames=6))
    stamps = []
    for i, frame in enumerate(camera.frames()):
        stamps.append(frame.timestamp)
        if i == 1:
            time.sleep(0.25)  # the loop falls behind by five frame periods
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    assert all(abs(g - 0.05) < 0.005 for g in gaps), gaps  # catch-up frames keep their own 50 ms apart


def test_a_frame_older_than_the_limit_is_an_error_not_a_late_reject(tmp_path):
    loaded = load_recipe(DEMO)
    assert frame_age_limit_s(loaded) == pytest.approx(1.5)  # the actuator's 600 mm at 400 mm/s
    assert frame_age_limit_s(load_recipe(DEMO, ["camera.max_frame_age_ms=200"])) == pytest.approx(0.2)
    frame = next(iter(ReplayCamera(ReplaySettings(path=str(FIXTURE), max_frames=1)).frames()))
    outcome = inspect_frame(frame, "P1", None, loaded, None, age_limit_s=1.5, clock=lambda: frame.timestamp + 1.8)
    assert outcome.part.verdict.status is Status.ERROR and "1800 ms after its capture" in outcome.part.error


@pytest.mark.parametrize("stamp, says", [
    (float("nan"), "the camera stamped it nan, not a time"),
    (None, "the camera stamped it None, not a time"),
    (1000.0 + 3600.0, "stamped it 3600.0 s ahead of this computer's clock"),
])
def test_a_frame_stamped_off_this_computers_clock_is_an_error_timed_from_now(stamp, says):
    # the outputs time each reject from the stamp: a NaN would never fall due, an hour ahead an hour late
    loaded = load_recipe(DEMO)
    frame = next(iter(ReplayCamera(ReplaySettings(path=str(FIXTURE), max_frames=1)).frames()))
    for item in (replace(frame, timestamp=stamp), FrameError("000000", 0, "cut short", stamp)):
        outcome = inspect_frame(item, "P1", None, loaded, None, age_limit_s=1.5, clock=lambda: 1000.0)
        assert outcome.part.verdict.status is Status.ERROR and says in outcome.part.error, outcome.part.error
        assert outcome.part.timestamp == 1000.0
    in_time = inspect_frame(FrameError("000000", 0, "cut short", 1000.5), "P1", None, loaded, None, clock=lambda: 1000.0)
    assert in_time.part.timestamp == 1000.5 and in_time.part.error == "cut short"  # within the clock's slack


def test_the_zed_driver_stamps_the_capture_not_the_read():
    # V4L2 hands OpenCV the buffer's monotonic timestamp: a frame that waited 120 ms in the queue is 120 ms old
    assert capture_time(pos_msec=1000.0 * (50.0 - 0.12), wall_now=1000.0, monotonic_now=50.0, asked=999.99) \
        == pytest.approx(1000.0 - 0.12)
    # no plausible timestamp from the backend: the moment the frame was asked for, never the read's end
    assert capture_time(0.0, wall_now=1000.0, monotonic_now=50.0, asked=999.9) == 999.9
    assert capture_time(1e9, wall_now=1000.0, monotonic_now=50.0, asked=999.9) == 999.9

