"""``inspect eval repeatability``: one part captured several times, inspected capture by capture as the line inspects a
plate, and held to the same verdict and to the uncertainty it reports (``core.repeatability``)."""
from __future__ import annotations

import hashlib
import json
from collections import Counter
from pathlib import Path

import click

from core.commands.params import cuda_if_present, demo_recipe, out_folder
from core.recipe.schema import MAX_THREADS


@click.command("repeatability")
@click.argument("parts", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--recipe", default=demo_recipe(), type=click.Path(path_type=Path), show_default=True,
              help="the line's detector, stereo, depth and rules (its camera is not used)")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE", help="override a recipe value")
@click.option("--out", type=click.Path(path_type=Path), default=Path("runs/repeatability"), show_default=True,
              callback=out_folder)
@click.option("--device", default="cpu", show_default=True, callback=cuda_if_present, help="cpu, cuda or auto")
@click.option("--threads", type=click.IntRange(1, MAX_THREADS), default=None, help="torch and OpenCV CPU threads")
@click.option("--boxes", type=click.Choice(["detector", "labels"]), default="detector", show_default=True,
              help="measure in the recipe's detector's boxes, as the line does, or in each capture's labelled boxes "
                   "(labels/FRAME.json), which leaves the detector out of the scatter")
def repeatability_command(parts, recipe, overrides, out, device, threads, boxes) -> None:
    """Each of PARTS: a folder of one part captured several times as it stands under the camera (`inspect camera
    record` with the part held still, or `inspect sim generate --captures N`, whose labels name each plate of a
    folder of several, each then studied on its own), inspected capture by capture as the line inspects a plate.
    Per defect: how often it was found, its deviation's and distance's scatter over the captures against the
    uncertainty reported with them, and what its rules proved. Exit 1 where a part's verdict
    differs between captures, a defect is found only sometimes or proven on both sides of a limit, a
    measurement scatters more than its uncertainty allows at 99 % confidence, or it drifts over the captures in
    the order taken (`inspect camera record --every`: a camera warming up): such a line does not decide alike on
    the same part, or reports an uncertainty this camera does not meet. Where the captures are labelled
    (`inspect data draft-labels`), the first capture's labels name the part's defects, each counted however
    seldom it is found. Saves JSON and Markdown."""
    from core.commands.inspection import _load, distinct_folders, fail, replay_of
    from core.depth import DepthRule
    from core.engine import Pipeline, SetupError, build_detector, command_threads, make_plugin, plugin_context
    from core.registry import default_registry
    from drivers.file_writes import write_text

    distinct_folders(parts, "a folder of captures")
    loaded = _load(recipe, overrides)
    command_threads(threads)
    registry = default_registry()
    ctx = plugin_context(loaded, device)
    shown = {}  # each folder's captures: what each frame's labels say and which plate it shows
    for folder in parts:  # before the model loads: a folder that cannot hold a study is said at once
        camera = replay_of(folder, registry, ctx)
        try:
            shown[folder] = _check_captures(folder, camera.frames(), boxes)
        finally:
            camera.close()
    try:
        stereo = make_plugin(loaded, registry, ctx, "stereo", loaded.recipe.stereo.backend, "stereo",
                             loaded.plugin_settings["stereo"])
        detector = build_detector(loaded, registry, ctx)
    except SetupError as exc:
        fail(str(exc))
    rule = DepthRule.from_recipe(loaded.recipe)
    studies = []
    for folder in parts:
        pipeline = Pipeline(replay_of(folder, registry, ctx), stereo, detector, [])
        if not studies:
            pipeline.warm_up()
        try:
            studies += _study(folder, pipeline, loaded, rule, boxes, shown[folder])
        finally:
            pipeline.close()
    text = "\n\n".join(s.markdown() for s in studies)
    click.echo(text)
    write_text(out / "repeatability.md", text + "\n")
    write_text(out / "repeatability.json", json.dumps(
        {"recipe": str(loaded.path), "parts": [s.to_json() for s in studies]}, indent=2) + "\n")
    click.echo("")
    findings = [(s, f) for s in studies for f in s.findings()]
    for study in studies:
        click.echo(study.summary())
    for study, finding in findings:
        click.echo(f"  {study.part}: {finding}")
    click.echo(f"wrote {out / 'repeatability.md'}, {out / 'repeatability.json'}")
    if findings:
        raise SystemExit(1)


def _check_captures(folder: Path, frames, boxes: str) -> dict:
    """Each capture of ``frames`` (``folder``'s) by frame id: (the plate it shows, its labels or None), the plate
    its labels' ``plate`` (``inspect sim generate --captures`` renders several in a row), else, for a capture that
    cannot be read, the plate of the capture before it (it was taken among its plate's), else None (a folder of one
    part). A one-line error (exit 2) where the captures cannot make a study: fewer than two of a plate, two with
    the same images (which measure alike whatever the camera's noise), labels that cannot be read, or a capture
    without labels where ``boxes`` is "labels"."""
    from core.commands.inspection import fail
    from drivers.sequence_folder import SequenceError, read_labels

    shown, images, plate = {}, {}, None
    for item in frames:
        labels = None
        if hasattr(item, "left"):
            digest = hashlib.sha256(item.left.tobytes() + item.right.tobytes()).hexdigest()
            if digest in images:
                fail(f"{folder}: frames {images[digest]} and {item.frame_id} hold the same images: a camera that "
                     f"delivered its last frame again, or a copied file; a repeatability study needs captures of "
                     f"their own")
            images[digest] = item.frame_id
            if "labels" in item.meta:
                try:
                    labels = read_labels(item.meta["labels"], item.left.shape[:2])
                except SequenceError as exc:
                    fail(str(exc))
            elif boxes == "labels":
                fail(f"{folder}: frame {item.frame_id} has no labels/{item.frame_id}.json (--boxes labels measures "
                     f"in its labelled boxes)")
            plate = None if labels is None else labels.get("plate")
        shown[item.frame_id] = (plate, labels)
    counts = Counter(plate for plate, _ in shown.values()) or Counter({None: 0})
    for plate, count in counts.items():
        if count < 2:
            of = "" if plate is None else f" of plate {plate}"
            fail(f"{folder}: {count} capture{of}; a repeatability study needs two or more of the same part")
    return shown


def _study(folder: Path, pipeline, loaded, rule, boxes: str, shown: dict) -> list:
    """The captures in ``folder`` (``pipeline.camera`` plays them), each inspected as the line inspects a plate
    (``core.engine.inspect_frame``), in the detector's boxes or (``boxes`` "labels") in its labelled ones: a study
    of each plate ``shown`` (``_check_captures``) names (one for a folder of one part), whose first capture's labels
    name its defects."""
    from core import repeatability as rp
    from core.decision import judge_defect
    from core.engine import Detected, inspect_frame
    from core.types import Detection

    # an undecided measurement proves neither side, whatever the recipe then does with the part
    proving = loaded.recipe.decision.model_copy(update={"uncertain": "flag"})
    captures, labelled = {}, {}
    for item in pipeline.camera.frames():
        plate, labels = shown[item.frame_id]
        if labels is not None and plate not in labelled:
            labelled[plate] = tuple(rp.Labelled(d["class"], tuple(d["box"]), d.get("deviation_mm"))
                                    for d in labels["defects"])
        detected = None
        if boxes == "labels" and labels is not None:
            detected = Detected([Detection(d["class"], 1.0, tuple(d["box"])) for d in labels["defects"]])
        outcome = inspect_frame(item, f"capture-{item.frame_id}", pipeline, loaded, rule, detected)
        readings = tuple(
            rp.Reading(m.detection.class_name, tuple(float(v) for v in m.detection.box), m.deviation_mm,
                       m.deviation_sigma_mm, m.distance_mm, m.distance_sigma_mm, judge_defect(m, proving)[0])
            for m in outcome.part.measurements)
        captures.setdefault(plate, []).append(
            rp.Capture(item.frame_id, outcome.part.verdict.status, readings, outcome.part.error or ""))
    return [rp.Study(str(folder) if len(captures) == 1 else f"{folder} plate {plate}", tuple(shot),
                     labelled.get(plate, ())) for plate, shot in captures.items()]


def register(cli: click.Group) -> None:
    cli.commands["eval"].add_command(repeatability_command, "repeatability")
