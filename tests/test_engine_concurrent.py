"""``stereo.concurrent``: the next frame is detected while this one is measured; nothing else changes."""
from __future__ import annotations

import sqlite3
import threading

import numpy as np
import pytest

import stereo_inspect_fixed_roi
from conftest import write_recipe
from test_engine import RECIPE, BrokenCameraPlugin

from core import engine
from core.contracts import PluginSpec
from core.hookspecs import hookimpl
from core.recipe import load_recipe
from core.registry import Registry, make_manager
from core.types import Detection, Status


def _run(tmp_path, info, overrides=(), registry=None, max_frames=None):
    registry = registry or Registry(make_manager((stereo_inspect_fixed_roi,)))
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log"))
    loaded = load_recipe(path, list(overrides), registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu", max_frames=max_frames)
    return summary, seen


def test_same_verdicts_and_depths_as_one_frame_at_a_time(tmp_path, plane_sequence):
    info = plane_sequence([0.0, 6.0, 0.5, 6.0])
    (info["folder"] / "left" / "000002.png").write_bytes(b"garbage")  # a FrameError in the middle
    _, plain = _run(tmp_path, info, ["results.path=results_a"])
    summary, ahead = _run(tmp_path, info, ["results.path=results_b", "stereo.concurrent=true"])
    assert [o.part.verdict.status for o in ahead] == [o.part.verdict.status for o in plain] == \
        [Status.PASS, Status.REJECT, Status.ERROR, Status.REJECT]
    for a, b in zip(plain, ahead):
        assert a.part.frame_id == b.part.frame_id
        assert [m.deviation_mm for m in a.part.measurements] == [m.deviation_mm for m in b.part.measurements]
        assert ("detection" in b.timings) == (b.part.verdict.status is not Status.ERROR)
    assert summary.frames == 4 and not any(t.name == "detect-ahead" for t in threading.enumerate())


def test_stopping_early_ends_the_detection_thread(tmp_path, plane_sequence):
    info = plane_sequence([6.0] * 5)
    summary, seen = _run(tmp_path, info, ["stereo.concurrent=true"], max_frames=2)
    assert len(seen) == 2 and summary.frames == 2
    assert not any(t.name == "detect-ahead" for t in threading.enumerate())


def test_camera_that_raises_is_still_an_alarm(tmp_path, plane_sequence):
    info = plane_sequence([0.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, BrokenCameraPlugin())))
    text = RECIPE.format(box=info["box"], output="log").replace("plugin: replay\n  settings: {path: seq}", "plugin: broken")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), ["stereo.concurrent=true"], registry=registry)
    summary = engine.run(loaded, registry=registry, device="cpu")
    assert summary.exit_code == engine.EXIT_ALARMS and "USB device vanished" in summary.alarms[0].message


def numba_interrupted() -> SystemError:
    """What a Ctrl-C landing inside a numba function compiled with nogil raises (tests/test_interrupts.py)."""
    try:
        raise KeyboardInterrupt
    except KeyboardInterrupt as interrupt:
        error = SystemError("CPUDispatcher(<function _system>) returned a result with an exception set")
        error.__cause__ = interrupt
        return error


class InterruptedStereo:
    """A matcher whose second frame is interrupted (Ctrl-C while that part is being measured), the interrupt
    coming out as ``raises`` makes it."""

    name = "interrupted"

    def __init__(self, raises):
        self.calls = 0
        self.raises = raises

    def compute(self, left, right, min_disp, max_disp):
        self.calls += 1
        if self.calls == 2:
            raise self.raises()
        return np.full(left.shape[:2], 90.0, dtype=np.float32)


class InterruptedStereoPlugin:
    def __init__(self, raises=KeyboardInterrupt):
        self.raises = raises

    @hookimpl
    def stereo_inspect_stereo_backends(self):
        return [PluginSpec("interrupted", "stereo", lambda s, ctx: InterruptedStereo(self.raises))]


@pytest.mark.parametrize("raises", [KeyboardInterrupt, numba_interrupted], ids=["plain", "from-numba"])
@pytest.mark.parametrize("concurrent", ["false", "true"])
def test_an_interrupted_run_rejects_every_part_it_read_and_did_not_finish(tmp_path, plane_sequence, concurrent,
                                                                        raises):
    """Ctrl-C in the middle of a part: that part, and the next one detection had already read, are ERROR
    (rejected, stored, sent to the outputs), not lost; the other parts are not read. Coming out of a numba
    kernel as a SystemError, it was that part's "stereo failed" ERROR, and the run went on."""
    info = plane_sequence([0.0] * 6)
    registry = Registry(make_manager((stereo_inspect_fixed_roi, InterruptedStereoPlugin(raises))))
    text = RECIPE.format(box=info["box"], output="log").replace("backend: opencv_sgbm", "backend: interrupted")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), [f"stereo.concurrent={concurrent}"], registry=registry)
    summary = engine.run(loaded, registry=registry, device="cpu")
    assert summary.interrupted and summary.exit_code == engine.EXIT_INTERRUPTED
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    parts = db.execute("SELECT frame_id, verdict, error FROM parts ORDER BY frame_id").fetchall()
    assert [p[0] for p in parts] == [f"{i:06d}" for i in range(len(parts))]
    assert len(parts) in ((2,) if concurrent == "false" else (2, 3, 4))  # ahead: the frames read while measuring
    assert "not inspected" not in (parts[0][2] or "")  # measured (by a matcher that knows nothing: its verdict)
    assert all(v == "ERROR" and "not inspected: the run stopped first" in e for _, v, e in parts[1:])
    assert db.execute("SELECT parts FROM runs").fetchone()[0] == len(parts)
    sent = {r[0] for r in db.execute("SELECT part_id FROM output_events WHERE output = 'log' AND command LIKE 'REJECT%'")}
    assert sent == {r[0] for r in db.execute("SELECT part_id FROM parts WHERE verdict != 'PASS'")}


class InterruptingOutput:
    """An output in whose hands the first part is when Ctrl-C comes: that part is already stored."""

    def __init__(self):
        self.parts = []

    def submit(self, part):
        self.parts.append(part.part_id)
        if len(self.parts) == 1:
            raise KeyboardInterrupt

    def poll(self):
        return []

    def close(self, timeout_s=10.0):
        return []


class InterruptingOutputPlugin:
    output = None

    @hookimpl
    def stereo_inspect_outputs(self):
        def make(settings, ctx):
            InterruptingOutputPlugin.output = InterruptingOutput()
            return InterruptingOutputPlugin.output
        return [PluginSpec("interrupting", "output", make)]


@pytest.mark.parametrize("concurrent", ["false", "true"])
def test_a_part_stored_before_the_interrupt_keeps_its_verdict(tmp_path, plane_sequence, concurrent):
    """Ctrl-C while the first part is handed to the first of two outputs: the part keeps its stored verdict,
    the second output still gets it, and the first raises an alarm, since it may not have."""
    info = plane_sequence([6.0] * 4)
    registry = Registry(make_manager((stereo_inspect_fixed_roi, InterruptingOutputPlugin())))
    text = RECIPE.format(box=info["box"], output="interrupting\n  - plugin: log")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), [f"stereo.concurrent={concurrent}"], registry=registry)
    summary = engine.run(loaded, registry=registry, device="cpu")
    assert summary.exit_code == engine.EXIT_INTERRUPTED
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    parts = db.execute("SELECT part_id, verdict FROM parts ORDER BY part_id").fetchall()
    assert parts[0] == ("R1-000000", "REJECT")  # measured and stored: not turned into an ERROR afterwards
    assert all(v == "ERROR" for _, v in parts[1:])  # detection ahead had read more: rejected, not lost
    assert len({p for p, _ in parts}) == len(parts) == (1 if concurrent == "false" else len(parts))
    assert InterruptingOutputPlugin.output.parts == [p for p, _ in parts]  # each handed to the output once
    logged = {r[0] for r in db.execute("SELECT part_id FROM output_events WHERE output = 'log'")}
    assert logged == {p for p, _ in parts}
    alarms = db.execute("SELECT source, part_id, message FROM alarms").fetchall()
    assert [(s, p) for s, p, _ in alarms] == [("interrupting", "R1-000000")] and "may not have received" in alarms[0][2]


class WarmStereo:
    """Records its calls: ``warm_up`` must come once, before the first part's ``compute``."""

    def __init__(self):
        self.calls = []

    def warm_up(self):
        self.calls.append("warm_up")

    def compute(self, left, right, min_disp, max_disp):
        self.calls.append("compute")
        return np.full(left.shape[:2], (min_disp + max_disp) / 2, dtype=np.float32)


def test_the_stereo_backends_optional_warm_up_runs_once_before_the_first_part(tmp_path, plane_sequence):
    info = plane_sequence([0.0] * 2)
    stereo = WarmStereo()

    class Plugin:
        @hookimpl
        def stereo_inspect_stereo_backends(self):
            return [PluginSpec("warm", "stereo", lambda s, ctx: stereo)]

    registry = Registry(make_manager((stereo_inspect_fixed_roi, Plugin())))
    text = RECIPE.format(box=info["box"], output="log").replace("backend: opencv_sgbm", "backend: warm")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry)
    engine.run(loaded, registry=registry, device="cpu")
    assert stereo.calls[0] == "warm_up" and stereo.calls.count("warm_up") == 1 and "compute" in stereo.calls


class InTurnDetector:
    """Hands out the boxes of the frames in turn, as an evaluation's detector of true boxes does: it must be
    called once per part and for nothing else. ``warm_up`` where given."""

    class_names = ["pit"]

    def __init__(self, boxes, warm):
        self.boxes, self.calls = list(boxes), []
        if warm:
            self.warm_up = lambda: self.calls.append("warm_up")

    def detect(self, image):
        self.calls.append(image.shape)
        return [Detection("pit", 0.9, self.boxes.pop(0))] if self.boxes else []


@pytest.mark.parametrize("warm", [False, True])
@pytest.mark.parametrize("concurrent", [False, True])
def test_the_detector_sees_the_parts_alone_and_its_optional_warm_up_comes_first(tmp_path, plane_sequence, warm,
                                                                                 concurrent):
    # the engine had warmed every detector up with a call on a blank image: a detector handing out each frame's
    # true boxes in turn then measured every part in the boxes of the part before
    info = plane_sequence([0.0, 6.0, 0.5])
    detector = InTurnDetector([tuple(info["box"])] * 3, warm)

    class Plugin:
        @hookimpl
        def stereo_inspect_detectors(self):
            return [PluginSpec("in_turn", "detector", lambda s, ctx: detector)]

    registry = Registry(make_manager((stereo_inspect_fixed_roi, Plugin())))
    text = RECIPE.format(box=info["box"], output="log").replace("plugin: fixed_roi", "plugin: in_turn")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), [f"stereo.concurrent={str(concurrent).lower()}"],
                         registry=registry)
    seen = []
    engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    shape = (info["calib"].height, info["calib"].width, 3)
    assert detector.calls == ["warm_up"] * warm + [shape] * 3
    assert [o.part.verdict.status for o in seen] == [Status.PASS, Status.REJECT, Status.PASS]


def test_the_surface_fit_is_warmed_up_before_the_first_part(tmp_path, plane_sequence, monkeypatch):
    from core import depth, surface_fit

    calls = []
    warm, measure = surface_fit.warm_up, depth.measure_defect
    monkeypatch.setattr(surface_fit, "warm_up", lambda: calls.append("warm_up") or warm())
    monkeypatch.setattr(depth, "measure_defect", lambda *a, **k: calls.append("measure") or measure(*a, **k))
    info = plane_sequence([0.0] * 2)
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log")),
                         registry=Registry(make_manager((stereo_inspect_fixed_roi,))))
    engine.run(loaded, registry=Registry(make_manager((stereo_inspect_fixed_roi,))), device="cpu")
    assert calls[0] == "warm_up" and calls.count("warm_up") == 1 and "measure" in calls
