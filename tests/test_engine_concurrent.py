"""``stereo.concurrent``: the next frame is detected while this one is measured; nothing else changes."""
from __future__ import annotations

import threading

import stereo_inspect_fixed_roi
from conftest import write_recipe
from test_engine import RECIPE, BrokenCameraPlugin

from core import engine
from core.recipe import load_recipe
from core.registry import Registry, make_manager
from core.types import Status


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
