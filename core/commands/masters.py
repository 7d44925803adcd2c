"""``inspect data draft-labels``: a recording of master parts given labels drafted from the recipe's detector,
their depths left for the engineer to measure on the plates (``core.verification``)."""
from __future__ import annotations

import json
from pathlib import Path

import click

from core.commands.params import demo_recipe

NEXT_STEPS = ("fill in each defect's deviation_mm as measured on the plate (mm, + below the surface), remove boxes "
              "on sound plate and add the defects the detector missed; then name the folder in the recipe's "
              "verify.path")


def draft(frame_id: str, detections: list) -> dict:
    """The labels of one master frame from its ``detections`` (``core.types.Detection``): each box and class,
    its confidence for the engineer's eye, and no depth (``deviation_mm`` null until measured on the plate)."""
    return {"frame_id": frame_id, "defects": [
        {"class": d.class_name, "box": [round(float(v), 1) for v in d.box], "confidence": round(float(d.confidence), 3),
         "deviation_mm": None} for d in detections]}


@click.command("draft-labels")
@click.argument("folder", type=click.Path(path_type=Path))
@click.option("--recipe", default=demo_recipe(), type=click.Path(path_type=Path), show_default=True,
              help="its detector, confidence and classes draw the boxes (its camera is not used)")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE", help="override a recipe value")
def draft_labels_command(folder: Path, recipe: Path, overrides: tuple[str, ...]) -> None:
    """Draft labels/FRAME.json for each frame of FOLDER (master parts recorded with `inspect camera record`)
    that has none: the recipe's detector's boxes, each defect's deviation_mm left null. Frames already
    labelled are left as they are; nothing is written if a frame cannot be read or detected on."""
    from core.commands.inspection import _load, fail, replay_of
    from core.engine import SetupError, build_detector, kept_detections, plugin_context
    from core.interrupts import raise_if_interrupted
    from core.registry import default_registry
    from drivers.file_writes import write_text

    if not folder.is_dir():
        fail(f"{folder}: not a sequence folder")
    loaded = _load(recipe, overrides)
    registry = default_registry()
    ctx = plugin_context(loaded, "cpu")
    camera = replay_of(folder, registry, ctx)
    try:
        detector = build_detector(loaded, registry, ctx)
    except SetupError as exc:
        fail(str(exc))
    labels = folder / "labels"
    drafts, kept = {}, []
    for frame in camera.frames():
        if (labels / f"{frame.frame_id}.json").exists():
            kept.append(frame.frame_id)
            continue
        if not hasattr(frame, "left"):  # a FrameError: a master part that cannot be read is one to record again
            fail(f"{folder}: {frame.said}")
        try:
            found = detector.detect(frame.left)
        except Exception as exc:
            raise_if_interrupted(exc)
            fail(f"{folder}: frame {frame.frame_id}: the detector failed: {type(exc).__name__}: {exc}")
        found, problem = kept_detections(found, detector, loaded.recipe, frame.left.shape[:2])
        if problem is not None:
            fail(f"{folder}: frame {frame.frame_id}: {problem}")
        drafts[frame.frame_id] = draft(frame.frame_id, found)
    camera.close()  # a folder without frames its factory refused
    if not drafts:
        click.echo(f"{labels}: every frame is labelled already; nothing written")
        return
    labels.mkdir(exist_ok=True)
    for frame_id, labelled in drafts.items():
        write_text(labels / f"{frame_id}.json", json.dumps(labelled, indent=2) + "\n")
    boxes = sum(len(d["defects"]) for d in drafts.values())
    click.echo(f"wrote {len(drafts)} labels ({boxes} boxes) to {labels}"
               + (f"; {len(kept)} frames already labelled, left as they were" if kept else ""))
    click.echo(f"next: {NEXT_STEPS}")


def register(cli: click.Group) -> None:
    cli.commands["data"].add_command(draft_labels_command)
