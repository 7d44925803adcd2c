"""The whole loop on exact synthetic plates, with the example detector registered in-process."""
from __future__ import annotations

import re
import shutil
import sqlite3
from pathlib import Path

import cv2
import numpy as np
import pytest
import stereo_inspect_fixed_roi
from conftest import write_recipe

from core import engine
from core.hookspecs import hookimpl
from core.contracts import PluginSpec
from core.recipe import load_recipe
from core.registry import Registry, make_manager
from core.store import ResultsStore
from core.types import OutputEvent, Status

RECIPE = """\
name: engine-test
camera:
  plugin: replay
  settings: {{path: seq}}
stereo:
  backend: opencv_sgbm
  working_distance_mm: [300, 600]
  schedule: every_frame
detector:
  plugin: fixed_roi
  settings:
    regions:
      - {{name: pit, box: {box}}}
decision:
  rules:
    - {{class: any, quantity: deviation_mm, op: ">", threshold: 1.5}}
outputs:
  - plugin: {output}
results:
  path: results
  save_images: rejected
"""


class StoreWitness:
    """An output that checks, at the moment it is handed a part, that the store already holds it."""

    seen: list[tuple[str, bool]] = []

    def __init__(self, db_path):
        self.db_path = db_path

    def submit(self, part):
        with sqlite3.connect(self.db_path) as db:
            row = db.execute("SELECT verdict FROM parts WHERE part_id = ?", (part.part_id,)).fetchone()
        StoreWitness.seen.append((part.part_id, row is not None and row[0] == part.verdict.status.value))

    def poll(self):
        return []

    def close(self, timeout_s=10.0):
        return [OutputEvent("witness", None, "close", "delivered", 0.0)]


class WitnessPlugin:
    @hookimpl
    def stereo_inspect_outputs(self):
        return [PluginSpec("witness", "output", lambda s, ctx: StoreWitness(ctx.recipe_dir / "results" / "results.db"))]


@pytest.fixture
def registry():
    return Registry(make_manager((stereo_inspect_fixed_roi, WitnessPlugin())))


def _run(tmp_path, registry, info, output="log"):
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output=output))
    loaded = load_recipe(path, registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    return summary, seen


def test_deep_pit_rejected_shallow_and_flat_pass(tmp_path, plane_sequence, registry):
    info = plane_sequence([0.0, 0.5, 6.0])
    summary, seen = _run(tmp_path, registry, info)
    assert [o.part.verdict.status for o in seen] == [Status.PASS, Status.PASS, Status.REJECT]
    deep = seen[2].part.measurements[0]
    assert deep.distance_mm == pytest.approx(400, abs=5)
    assert deep.deviation_mm > 1.5
    assert "deviation_mm" in seen[2].part.verdict.reasons[0]
    assert summary.exit_code == engine.EXIT_OK and summary.counts[Status.REJECT] == 1
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert db.execute("SELECT COUNT(*) FROM parts").fetchone()[0] == 3
    row = db.execute("SELECT d.class, d.deviation_mm, d.verdict FROM defects d JOIN parts p ON p.id = d.part_row WHERE p.verdict='REJECT'").fetchone()
    assert row[0] == "pit" and row[1] == pytest.approx(deep.deviation_mm) and row[2] == "REJECT"
    assert (tmp_path / "results" / "images" / f"{seen[2].part.part_id}.jpg").exists()
    assert not (tmp_path / "results" / "images" / f"{seen[0].part.part_id}.jpg").exists()
    assert db.execute("SELECT outcome FROM output_events").fetchall() == [("delivered",)]


def test_corrupt_frame_is_an_error_and_the_run_goes_on(tmp_path, plane_sequence, registry):
    info = plane_sequence([0.0, 6.0, 0.0])
    (info["folder"] / "left" / "000000.png").write_bytes(b"garbage")
    summary, seen = _run(tmp_path, registry, info)
    assert [o.part.verdict.status for o in seen] == [Status.ERROR, Status.REJECT, Status.PASS]
    assert "000000.png" in seen[0].part.verdict.reasons[0]
    assert summary.counts[Status.ERROR] == 1 and summary.exit_code == engine.EXIT_PART_ERRORS
    assert summary.alarms == []  # one bad frame is that part's ERROR, not a lost camera


def test_camera_lost_for_several_frames_is_one_alarm(tmp_path, plane_sequence, registry):
    info = plane_sequence([0.0] * 8)
    for i in (1, 2, 3, 4):  # an outage of four frames
        (info["folder"] / "left" / f"{i:06d}.png").unlink()
    summary, seen = _run(tmp_path, registry, info)
    assert [o.part.verdict.status for o in seen].count(Status.ERROR) == 4
    (alarm,) = summary.alarms
    assert alarm.source == "camera" and alarm.message.startswith("camera lost: 3 frames in a row")
    assert "000003" in alarm.message and alarm.part_id == seen[3].part.part_id
    assert summary.exit_code == engine.EXIT_ALARMS
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    assert db.execute("SELECT source, part_id FROM alarms").fetchall() == [("camera", seen[3].part.part_id)]


def test_a_display_that_fails_does_not_keep_an_alarm_from_the_store(tmp_path, plane_sequence, registry):
    # the operator's display (on_event) raising, as a console whose pipe closed does, left the alarm unstored
    info = plane_sequence([0.0] * 5)
    for i in (1, 2, 3):
        (info["folder"] / "left" / f"{i:06d}.png").unlink()

    def gone(event):
        raise BrokenPipeError(32, "Broken pipe")

    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log"))
    summary = engine.run(load_recipe(path, registry=registry), registry=registry, on_event=gone, device="cpu")
    assert summary.frames == 5 and len(summary.alarms) == 1
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    assert db.execute("SELECT message FROM alarms").fetchone()[0].startswith("camera lost")
    assert db.execute("SELECT status FROM runs").fetchone()[0] == "finished"


def test_a_frozen_camera_rejects_every_repeated_frame_with_one_alarm(tmp_path, plane_sequence, registry):
    info = plane_sequence([0.0, 0.0, 0.0, 0.0, 0.0, 6.0])
    for side in ("left", "right"):  # frames 2-4 are frame 1's images again, as a stalled driver hands them over
        for i in (2, 3, 4):
            shutil.copy(info["folder"] / side / "000001.png", info["folder"] / side / f"{i:06d}.png")
    summary, seen = _run(tmp_path, registry, info)
    assert [o.part.verdict.status for o in seen] == [Status.PASS, Status.PASS] + [Status.ERROR] * 3 + [Status.REJECT]
    assert "frame 000001's images again" in seen[3].part.verdict.reasons[0]
    (alarm,) = summary.alarms
    assert alarm.source == "camera" and alarm.cause == "frozen" and alarm.message.startswith("camera frozen: frame 000002")
    assert alarm.part_id == seen[2].part.part_id and summary.exit_code == engine.EXIT_ALARMS
    from core.commands.inspection import alarm_hints
    hints = alarm_hints(summary.alarms, load_recipe(tmp_path / "r.yaml", registry=registry), plc_sim_given=False)
    assert any("same images again" in h for h in hints) and not any("stopped delivering" in h for h in hints)


def test_frames_that_cannot_show_a_defect_are_errors_and_an_outage_one_alarm(tmp_path, plane_sequence, registry):
    info = plane_sequence([0.0] * 7)
    rng = np.random.default_rng(0)
    for i in (1, 2, 3, 4):  # the lights fail for four frames: sensor noise on black
        dark = np.clip(rng.normal(3.0, 2.0, (192, 320, 3)), 0, 255).astype(np.uint8)
        for side in ("left", "right"):
            cv2.imwrite(str(info["folder"] / side / f"{i:06d}.png"), dark)
    cv2.imwrite(str(info["folder"] / "left" / "000006.png"), np.full((192, 320, 3), 128, np.uint8))  # a grey card
    summary, seen = _run(tmp_path, registry, info)
    assert [o.part.verdict.status for o in seen] == [Status.PASS] + [Status.ERROR] * 4 + [Status.PASS, Status.ERROR]
    assert "too dark to inspect" in seen[1].part.verdict.reasons[0] and "no texture" in seen[6].part.verdict.reasons[0]
    (alarm,) = summary.alarms
    assert alarm.cause == "image" and alarm.message.startswith("images unusable: 3 frames in a row (last: frame 000003")
    from core.commands.inspection import alarm_hints
    hints = alarm_hints(summary.alarms, load_recipe(tmp_path / "r.yaml", registry=registry), plc_sim_given=False)
    assert any("could not show a defect" in h for h in hints) and not any("stopped delivering" in h for h in hints)


def test_a_right_eye_that_cannot_see_or_repeats_the_left_is_an_error(tmp_path, plane_sequence, registry):
    info = plane_sequence([0.0] * 5)
    rng = np.random.default_rng(1)
    dark = np.clip(rng.normal(3.0, 2.0, (192, 320, 3)), 0, 255).astype(np.uint8)  # a covered right lens
    cv2.imwrite(str(info["folder"] / "right" / "000001.png"), dark)
    cv2.imwrite(str(info["folder"] / "right" / "000002.png"), np.full((192, 320, 3), 250, np.uint8))  # blinded
    shutil.copy(info["folder"] / "left" / "000003.png", info["folder"] / "right" / "000003.png")  # one eye as both
    summary, seen = _run(tmp_path, registry, info)
    assert [o.part.verdict.status for o in seen] == [Status.PASS] + [Status.ERROR] * 3 + [Status.PASS]
    assert "the right image is too dark to inspect" in seen[1].part.verdict.reasons[0]
    assert "the right image is washed out" in seen[2].part.verdict.reasons[0]
    assert "the left and right images are the same, byte for byte" in seen[3].part.verdict.reasons[0]
    (alarm,) = summary.alarms
    assert alarm.cause == "image" and alarm.message.startswith("images unusable: 3 frames in a row (last: frame 000003")


def test_plates_outside_the_working_distance_are_errors_and_a_run_of_them_one_alarm(tmp_path, plane_sequence,
                                                                                     registry):
    # the plates lie at 400 mm, the recipe searches 200-300 mm (a part of another thickness, a camera moved)
    info = plane_sequence([0.0, 6.0, 0.0, 0.0, 6.0])
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log"))
    loaded = load_recipe(path, ["stereo.working_distance_mm=[200, 300]"], registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR] * 5
    first = seen[0].part.measurements[0]
    assert first.distance_mm is None and first.surface_elsewhere_mm == pytest.approx(400, abs=4)
    assert "the plate lies outside the working distance" in first.note
    (alarm,) = summary.alarms
    assert alarm.cause == "range" and alarm.part_id == seen[2].part.part_id
    assert alarm.message.startswith("plates outside the working distance: 3 parts in a row whose images show the "
                                    "plate at about 40"), alarm.message
    assert "outside stereo.working_distance_mm (200-300 mm)" in alarm.message
    from core.commands.inspection import alarm_hints
    hints = alarm_hints(summary.alarms, loaded, plc_sim_given=False)
    assert any("outside the stereo search range" in h for h in hints)


def test_a_camera_with_its_eyes_swapped_costs_errors_and_a_run_of_them_one_alarm(tmp_path, plane_sequence, registry):
    info = plane_sequence([0.0, 6.0, 0.0, 0.0])
    folder = info["folder"]
    (folder / "left").rename(folder / "was_left")
    (folder / "right").rename(folder / "left")
    (folder / "was_left").rename(folder / "right")
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log"))
    loaded = load_recipe(path, ["stereo.working_distance_mm=[350, 500]"], registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR] * 4
    assert all(o.part.measurements[0].eyes_swapped for o in seen)
    (alarm,) = summary.alarms
    assert alarm.cause == "swapped" and alarm.part_id == seen[2].part.part_id
    from core.commands.inspection import alarm_hints
    hints = alarm_hints(summary.alarms, loaded, plc_sim_given=False)
    assert any("delivers its right eye's image as the left" in h for h in hints)


def test_a_camera_out_of_rectification_costs_errors_and_a_run_of_them_one_alarm(tmp_path, plane_sequence, registry):
    """The right eye's images two rows below the left's, as a calibration file of another camera leaves them: each
    part with a defect is an ERROR saying so, and three in a row one alarm."""
    info = plane_sequence([0.0, 6.0, 0.0, 0.0])
    for image in sorted((info["folder"] / "right").iterdir()):
        cv2.imwrite(str(image), np.roll(cv2.imread(str(image)), 2, axis=0))
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log"))
    loaded = load_recipe(path, ["stereo.working_distance_mm=[350, 500]"], registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR] * 4
    assert all(o.part.measurements[0].rows_apart_px == pytest.approx(2.0, abs=0.1) for o in seen)
    assert "the right eye's rows lie +2.0 px from the left eye's" in seen[0].part.verdict.reasons[0]
    (alarm,) = summary.alarms
    assert alarm.cause == "rectification" and alarm.part_id == seen[2].part.part_id


def _no_defects_recipe(tmp_path, info, working_distance):
    text = RECIPE.format(box=info["box"], output="log")
    text = re.sub(r"    regions:\n      - \{name: pit, box: [^}]*\}\n", "    regions: []\n", text)
    assert "regions: []" in text
    return load_recipe(write_recipe(tmp_path / "r.yaml", text),
                       [f"stereo.working_distance_mm={working_distance}"], registry=Registry(make_manager(
                           (stereo_inspect_fixed_roi,))))


@pytest.mark.parametrize("working_distance, swapped", [("[200, 300]", False), ("[500, 800]", False),
                                                      ("[300, 600]", True)])
def test_plates_without_defects_seen_where_no_search_looks_are_errors_and_a_run_of_them_one_alarm(
        tmp_path, plane_sequence, working_distance, swapped):
    # nothing found on them, so nothing measured: they passed wherever the plate was
    info = plane_sequence([0.0] * 4)
    if swapped:
        folder = info["folder"]
        (folder / "left").rename(folder / "was_left")
        (folder / "right").rename(folder / "left")
        (folder / "was_left").rename(folder / "right")
    loaded = _no_defects_recipe(tmp_path, info, working_distance)
    seen = []
    summary = engine.run(loaded, registry=Registry(make_manager((stereo_inspect_fixed_roi,))), on_part=seen.append,
                         device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR] * 4
    assert all(o.plate is not None and o.plate.swapped == swapped for o in seen)
    assert seen[0].plate.distance_mm == pytest.approx(400, abs=12)
    assert seen[0].part.error.startswith("frame 000000: no defect found, but the images ")
    (alarm,) = summary.alarms
    assert alarm.cause == ("swapped" if swapped else "range") and alarm.part_id == seen[2].part.part_id
    assert "they cannot be inspected and are rejected as ERROR" in alarm.message


def test_plates_without_defects_whose_eyes_rows_lie_apart_are_errors_and_a_run_of_them_one_alarm(
        tmp_path, plane_sequence):
    info = plane_sequence([0.0] * 4)
    for image in sorted((info["folder"] / "right").iterdir()):  # another camera's calibration: 4 rows off
        cv2.imwrite(str(image), np.roll(cv2.imread(str(image)), -4, axis=0))
    loaded = _no_defects_recipe(tmp_path, info, "[300, 600]")
    seen = []
    summary = engine.run(loaded, registry=Registry(make_manager((stereo_inspect_fixed_roi,))), on_part=seen.append,
                         device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR] * 4
    assert all(o.plate is not None and o.plate.rows_apart == -4 for o in seen)
    assert "only with the right eye's rows -4 px from the left eye's" in seen[0].part.error
    assert "cannot be checked does not pass" in seen[0].part.error
    (alarm,) = summary.alarms
    assert alarm.cause == "rectification" and alarm.part_id == seen[2].part.part_id
    assert "the right eye's rows -4.0 px from the left eye's" in alarm.message


def test_plates_without_defects_whose_images_match_nowhere_are_errors_and_a_run_of_them_one_alarm(
        tmp_path, plane_sequence):
    info = plane_sequence([0.0] * 4)
    rng = np.random.default_rng(3)
    for i in range(3):  # a damaged left image: detail enough, but not of the plate the right eye sees
        cv2.imwrite(str(info["folder"] / "left" / f"{i:06d}.png"), rng.integers(0, 256, (192, 320, 3), dtype=np.uint8))
    loaded = _no_defects_recipe(tmp_path, info, "[300, 600]")
    seen = []
    summary = engine.run(loaded, registry=Registry(make_manager((stereo_inspect_fixed_roi,))), on_part=seen.append,
                         device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR] * 3 + [Status.PASS]
    assert seen[0].plate is not None and seen[0].plate.unmatched >= 3
    assert "match at no shift" in seen[0].part.error and "cannot be checked does not pass" in seen[0].part.error
    (alarm,) = summary.alarms
    assert alarm.cause == "unmatched" and alarm.part_id == seen[2].part.part_id
    from core.commands.inspection import alarm_hints
    assert any("no common scene" in h for h in alarm_hints(summary.alarms, loaded, plc_sim_given=False))


def test_a_part_whose_defects_say_nothing_of_the_plate_is_located_by_its_frame(tmp_path, plane_sequence, registry):
    # a box at the left border, which the right camera does not see and whose ring cannot be scanned: the
    # part was an ERROR that did not say the plate lay outside the working distance, nor counted towards it
    plane_sequence([0.0] * 3)
    text = RECIPE.format(box=[1.0, 80.0, 21.0, 110.0], output="log")
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), ["stereo.working_distance_mm=[200, 300]"],
                         registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR] * 3
    first = seen[0]
    assert first.part.measurements[0].surface_elsewhere_mm is None and first.plate is not None
    assert first.plate.distance_mm == pytest.approx(400, abs=12)
    assert first.part.verdict.reasons[0].startswith("frame 000000: no defect could be measured, and the images show "
                                                    "the plate at ")
    (alarm,) = summary.alarms
    assert alarm.cause == "range" and alarm.part_id == seen[2].part.part_id


def test_plates_without_defects_within_the_working_distance_pass(tmp_path, plane_sequence):
    info = plane_sequence([0.0] * 2)
    loaded = _no_defects_recipe(tmp_path, info, "[300, 600]")
    seen = []
    summary = engine.run(loaded, registry=Registry(make_manager((stereo_inspect_fixed_roi,))), on_part=seen.append,
                         device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.PASS] * 2 and not summary.alarms
    assert all(o.plate is None and "plate check" in o.timings for o in seen)


def test_a_dead_disk_still_sends_the_decided_reject_then_stops_with_an_alarm(tmp_path, plane_sequence, registry,
                                                                              monkeypatch):
    info = plane_sequence([0.0, 6.0, 0.0, 0.0, 0.0])
    original = ResultsStore.record_part

    def read_only_from_the_second_part(store, run_id, part, verdicts):
        if part.index >= 1:  # as a disk that the system remounts read-only after an I/O error: SQLite refuses writes
            store.db.execute("PRAGMA query_only = ON")
        return original(store, run_id, part, verdicts)

    monkeypatch.setattr(ResultsStore, "record_part", read_only_from_the_second_part)
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log"))
    loaded = load_recipe(path, registry=registry)
    seen, events = [], []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, on_event=events.append, device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.PASS, Status.REJECT]  # then the run stopped
    sent = [e for e in events if isinstance(e, OutputEvent) and e.outcome == "delivered"]
    assert sent and sent[0].part_id == seen[1].part.part_id and "REJECT" in sent[0].command  # the reject went out
    # what was read ahead was rejected (not inspected), not dropped
    assert all("ERROR" in e.command for e in sent[1:])
    causes = [a.cause for a in summary.alarms]
    assert causes[0] == "store" and "readonly database" in summary.alarms[0].message
    assert summary.exit_code == engine.EXIT_ALARMS
    from core.commands.inspection import alarm_hints
    assert any("results store" in h for h in alarm_hints(summary.alarms, loaded, plc_sim_given=False))


def _run_with_images_refused(tmp_path, registry, info, refuse, settings=""):
    """The run with ``refuse(results folder)`` done first: every part, every event and the summary."""
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log") + settings)
    refuse(tmp_path / "results")
    seen, events = [], []
    summary = engine.run(load_recipe(path, registry=registry), registry=registry, on_part=seen.append,
                         on_event=events.append, device="cpu")
    with sqlite3.connect(tmp_path / "results" / "results.db") as db:
        stored = dict(db.execute("SELECT part_id, verdict FROM parts").fetchall())
    return summary, seen, events, stored


def _refused(kind):
    def refuse(results):
        images = results / "images"
        results.mkdir()
        if kind == "full disk":  # the first reject's image lands on /dev/full, which answers every write ENOSPC
            images.mkdir()
            (images / "R1-000001.jpg").symlink_to("/dev/full")
        elif kind == "a file in the way":
            images.write_text("not a folder")
    return refuse


@pytest.mark.parametrize("kind, why", [
    ("full disk", r"R1-000001\.jpg could not be written \(OSError: No space left on device\)"),
    ("a file in the way", r"images/R1-000001\.jpg could not be written \((FileExistsError|NotADirectoryError)"),
    ("below results.min_free_mb", r"the results disk has \d+ MB free, less than results\.min_free_mb \(1e\+12\)"),
])
def test_images_the_disk_refuses_cost_one_alarm_and_never_a_decision(tmp_path, plane_sequence, registry, kind, why):
    if kind == "full disk" and not Path("/dev/full").exists():
        pytest.skip("no /dev/full on this system to answer writes with a full disk")
    info = plane_sequence([0.0, 6.0, 6.0, 0.0, 6.0])
    settings = "  min_free_mb: 1.0e+12\n" if kind.startswith("below") else ""
    summary, seen, events, stored = _run_with_images_refused(tmp_path, registry, info, _refused(kind), settings)
    statuses = [o.part.verdict.status for o in seen]
    assert statuses == [Status.PASS, Status.REJECT, Status.REJECT, Status.PASS, Status.REJECT]  # the run went on
    assert stored == {o.part.part_id: o.part.verdict.status.value for o in seen}  # every decision stored
    sent = [e.part_id for e in events if isinstance(e, OutputEvent) and e.outcome == "delivered"]
    assert sent == [o.part.part_id for o in seen if o.part.verdict.status is Status.REJECT]
    (alarm,) = summary.alarms  # once, not once per reject
    assert alarm.cause == "images" and alarm.part_id == seen[1].part.part_id
    assert re.search(rf"annotated images are no longer saved: .*{why}.*; every part's decision is still stored",
                     alarm.message), alarm.message
    assert all(o.part.image_path is None for o in seen)
    assert not list((tmp_path / "results" / "images").glob("*.jpg"))
    from core.commands.inspection import alarm_hints
    hints = alarm_hints(summary.alarms, load_recipe(tmp_path / "r.yaml", registry=registry), plc_sim_given=False)
    assert any("every decision was still stored and sent" in h for h in hints)
    assert not any("results store could not be written" in h for h in hints)


def test_part_is_stored_before_outputs_see_it(tmp_path, plane_sequence, registry):
    StoreWitness.seen.clear()
    info = plane_sequence([0.0, 6.0])
    _run(tmp_path, registry, info, output="witness")
    assert len(StoreWitness.seen) == 2 and all(ok for _, ok in StoreWitness.seen)


def test_stereo_failure_rejects_the_part(tmp_path, plane_sequence, registry):
    info = plane_sequence([0.0])
    path = write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log"))
    loaded = load_recipe(path, registry=registry)
    # a range the image cannot hold, past the loader's check (a camera that states no geometry before it runs)
    stereo = loaded.recipe.stereo.model_copy(update={"working_distance_mm": (10.0, 600.0)})
    loaded.recipe = loaded.recipe.model_copy(update={"stereo": stereo})
    seen = []
    engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    assert seen[0].part.verdict.status is Status.ERROR
    assert "stereo failed" in seen[0].part.verdict.reasons[0] and "does not fit" in seen[0].part.verdict.reasons[0]


class BrokenCamera:
    def frames(self):
        yield from ()
        raise OSError("USB device vanished")

    def close(self):
        pass


class BrokenCameraPlugin:
    @hookimpl
    def stereo_inspect_cameras(self):
        return [PluginSpec("broken", "camera", lambda s, ctx: BrokenCamera())]


def _with_camera(tmp_path, plane_sequence, plugin, name: str):
    """(the loaded recipe, its registry): the engine's test recipe with the camera ``name`` that ``plugin``
    registers in place of the replay."""
    info = plane_sequence([0.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, plugin)))
    text = RECIPE.format(box=info["box"], output="log").replace("plugin: replay\n  settings: {path: seq}",
                                                                 f"plugin: {name}")
    return load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry), registry


def test_camera_that_raises_ends_the_run_with_an_alarm(tmp_path, plane_sequence):
    loaded, registry = _with_camera(tmp_path, plane_sequence, BrokenCameraPlugin(), "broken")
    summary = engine.run(loaded, registry=registry, device="cpu")
    assert summary.exit_code == engine.EXIT_ALARMS
    assert "USB device vanished" in summary.alarms[0].message
    db = sqlite3.connect(tmp_path / "results" / "results.db")
    assert db.execute("SELECT source FROM alarms").fetchall() == [("engine",)]
    assert db.execute("SELECT exit_code FROM runs").fetchone()[0] == engine.EXIT_ALARMS


class HalfACameraPlugin:
    """A factory that returns an object without the camera's methods (a plugin under development)."""

    @hookimpl
    def stereo_inspect_cameras(self):
        return [PluginSpec("half", "camera", lambda s, ctx: object())]


def test_a_plugin_object_without_its_kinds_methods_is_refused_before_the_run(tmp_path, plane_sequence):
    loaded, registry = _with_camera(tmp_path, plane_sequence, HalfACameraPlugin(), "half")
    with pytest.raises(engine.SetupError, match=r"camera: half: its factory returned an instance of object, which has no frames, "
                                                r"close \(a camera plugin's object needs them\)"):
        engine.run(loaded, registry=registry, device="cpu")
    assert not (tmp_path / "results").exists()  # refused before a run was recorded


@pytest.mark.parametrize("threads", [1, "auto"])
def test_the_recipe_sets_the_process_threads(tmp_path, plane_sequence, threads):
    """A station's torch and OpenCV threads come from the recipe (auto: half the cores), so that two
    inspections on one PC do not spin against each other."""
    import os

    import cv2
    import torch

    info = plane_sequence([0.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
    text = RECIPE.format(box=info["box"], output="log") + f"threads: {threads}\n"
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), registry=registry)
    seen = {}
    before = torch.get_num_threads(), cv2.getNumThreads()
    try:
        engine.run(loaded, registry=registry, device="cpu",
                   on_start=lambda _: seen.update(torch=torch.get_num_threads(), cv=cv2.getNumThreads()))
    finally:
        torch.set_num_threads(before[0])
        cv2.setNumThreads(before[1])
    expected = 1 if threads == 1 else max(1, (os.cpu_count() or 2) // 2)
    assert seen == {"torch": expected, "cv": expected}


def test_the_blas_libraries_run_on_one_thread(tmp_path, plane_sequence):
    """NumPy's (and OpenCV's) OpenBLAS threads, left spinning after the depth stage's small matrix products,
    slowed the next detection 2-3x on two cores: an inspection runs them on one thread."""
    from threadpoolctl import threadpool_info, threadpool_limits

    info = plane_sequence([0.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi,)))
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", RECIPE.format(box=info["box"], output="log") + "threads: 2\n"),
                         registry=registry)
    seen = []
    with threadpool_limits(2, user_api="blas"):  # as a fresh process on two cores starts
        engine.run(loaded, registry=registry, device="cpu",
                   on_start=lambda _: seen.extend(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"))
    assert seen and all(n == 1 for n in seen)


class OffImageDetectorPlugin:
    """A detector that reports a pit right of the image (a third-party detector with a coordinate bug)."""

    class Detector:
        class_names = ["pit"]

        def detect(self, image):
            from core.types import Detection
            h, w = image.shape[:2]
            return [Detection("pit", 0.9, (w + 10.0, 5.0, w + 40.0, 30.0))]

    @hookimpl
    def stereo_inspect_detectors(self):
        return [PluginSpec("offimage", "detector", lambda s, ctx: self.Detector())]


@pytest.mark.parametrize("region", ["defects", "full"])
def test_a_detection_outside_the_image_is_an_error_naming_it_never_a_pass(tmp_path, plane_sequence, region):
    info = plane_sequence([0.0, 0.0])
    registry = Registry(make_manager((stereo_inspect_fixed_roi, OffImageDetectorPlugin())))
    text = RECIPE.format(box=info["box"], output="log").replace("plugin: fixed_roi", "plugin: offimage")
    overrides = [f"stereo.region={region}"] + (["stereo.schedule=on_defect"] if region == "defects" else [])
    loaded = load_recipe(write_recipe(tmp_path / "r.yaml", text), overrides, registry=registry)
    seen = []
    summary = engine.run(loaded, registry=registry, on_part=seen.append, device="cpu")
    assert [o.part.verdict.status for o in seen] == [Status.ERROR, Status.ERROR]
    assert "detection failed: the detector returned a pit box" in seen[0].part.error
    assert "(330.0, 5.0, 360.0, 30.0) outside the 320x192 image" in seen[0].part.error
    assert summary.exit_code == engine.EXIT_PART_ERRORS


def _part(index, *measured):
    """A part with one defect per value of ``measured``: 'far' (the images show the plate outside the search),
    'swapped' (they show it only with the eyes exchanged), 'rows' (the eyes' rows 2.5 px apart), 'ok' (a deviation
    measured) or 'none' (no deviation, the plate nowhere else)."""
    from core.types import DefectMeasurement, Detection, PartResult, Verdict

    ms = [DefectMeasurement(Detection("pit", 0.9, (0, 0, 9, 9)), None if m != "ok" else 400.0,
                            0.5 if m == "ok" else None, 1.0, None, None, surface_elsewhere_mm=700.0 if m == "far" else None,
                            eyes_swapped=m == "swapped", rows_apart_px=2.5 if m == "rows" else None)
          for m in measured]
    return PartResult(f"P{index}", f"{index:06d}", index, 0.0, Verdict(Status.ERROR), ms)


def test_plates_out_of_range_alarm_once_per_run_of_them_and_a_measured_plate_ends_it():
    from core.recipe.schema import StereoSection

    watch = engine.SurfaceElsewhere(StereoSection(working_distance_mm=(350.0, 500.0)))
    alarms = [next(iter(watch.alarms(_part(i, *m))), None) for i, m in enumerate([
        ("far",), (), ("far", "none"), ("far",),  # a part without defects neither counts nor ends the run: 3rd far
        ("far",), ("ok",), ("far",), ("far",), ("none",), ("far",)])]  # the 4th stays quiet; "ok" ends the run,
    # a defect that could not be measured for another reason does not
    assert [i for i, a in enumerate(alarms) if a is not None] == [3, 9]
    assert alarms[3].cause == "range" and alarms[3].part_id == "P3" and "about 700 mm" in alarms[3].message
    assert "outside stereo.working_distance_mm (350-500 mm)" in alarms[3].message


def test_eyes_swapped_alarm_once_per_run_of_them_apart_from_the_range_s():
    from core.recipe.schema import StereoSection

    watch = engine.SurfaceElsewhere(StereoSection(working_distance_mm=(350.0, 500.0)))
    alarms = [watch.alarms(_part(i, *m)) for i, m in enumerate([
        ("swapped",), ("none",), ("swapped", "far"), ("swapped",), ("far",), ("far",),  # two runs side by side
        ("ok",), ("swapped",), ("swapped",)])]  # a measured plate ends both
    assert [(i, [a.cause for a in said]) for i, said in enumerate(alarms) if said] == [(3, ["swapped"]), (5, ["range"])]
    alarms = [a[0] if a else None for a in alarms]
    assert alarms[3].message.startswith("left and right images swapped: 3 parts in a row whose images show the plate "
                                        "within stereo.working_distance_mm (350-500 mm) only with "
                                        "the camera's left and right images exchanged (last: frame 000003)")


def test_a_camera_out_of_rectification_alarms_once_per_run_of_it():
    from core.commands.inspection import alarm_hints
    from core.recipe.schema import StereoSection

    watch = engine.SurfaceElsewhere(StereoSection(working_distance_mm=(350.0, 500.0)))
    alarms = [watch.alarms(_part(i, *m)) for i, m in enumerate([
        ("rows",), (), ("rows", "rows"), ("rows",), ("rows",), ("ok",), ("rows",), ("rows",), ("rows",)])]
    # a part without defects neither counts nor ends the run; one with a measured defect ends it
    assert [(i, [a.cause for a in said]) for i, said in enumerate(alarms) if said] == [(3, ["rectification"]),
                                                                                       (8, ["rectification"])]
    alarm = alarms[3][0]
    assert alarm.message == ("camera not rectified: 3 parts in a row whose images show the right eye's rows +2.5 px "
                             "from the left eye's (last: frame 000003); they cannot be inspected and are rejected as "
                             "ERROR until the camera's own calibration file is in the recipe")
    assert any("camera.settings.calibration is this camera's file" in h for h in alarm_hints([alarm], None, False))


def test_both_runs_reaching_their_alarm_on_one_part_raise_both():
    # one alarm per part was returned: the swapped eyes went unsaid while the range's run was told
    from core.recipe.schema import StereoSection

    watch = engine.SurfaceElsewhere(StereoSection(working_distance_mm=(350.0, 500.0)))
    said = [[a.cause for a in watch.alarms(_part(i, "far", "swapped"))] for i in range(4)]
    assert said == [[], [], ["range", "swapped"], []]
