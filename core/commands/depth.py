"""``inspect eval depth``: distance and deviation errors against a labelled sequence's truth."""
from __future__ import annotations

import platform
from pathlib import Path

import click

from core.commands.params import Finite, cuda_if_present, demo_recipe, out_folder
from core.recipe.schema import MAX_THREADS


@click.command("depth")
@click.argument("sequences", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--recipe", default=demo_recipe(), type=click.Path(path_type=Path), show_default=True,
              help="stereo, depth and decision settings come from here (its camera is not used)")
@click.option("--backend", default=None, help="stereo backend instead of the recipe's (with its default settings)")
@click.option("--set", "overrides", multiple=True, metavar="KEY.PATH=VALUE",
              help="override a recipe value, e.g. depth.method=disparity or stereo.settings.preset=seed (repeatable)")
@click.option("--out", type=click.Path(path_type=Path), default=Path("runs/depth_eval"), show_default=True,
              callback=out_folder)
@click.option("--figure/--no-figure", default=True, show_default=True, help="save error against distance and width")
@click.option("--device", default="cpu", show_default=True, callback=cuda_if_present,
              help="cpu, cuda or auto (torch_sgm)")
@click.option("--threads", type=click.IntRange(1, MAX_THREADS), default=None, help="torch and OpenCV CPU threads")
@click.option("--boxes", type=click.Choice(["true", "detector"]), default="true", show_default=True,
              help="measure in the labels' true boxes, or in the recipe's detector's boxes that match them")
@click.option("--box-scale", type=Finite(min=0.1, max=10.0), default=1.0, show_default=True,
              help="measure in the true boxes scaled about their centres, as a detector's looser or tighter boxes")
@click.option("--box-shift", type=Finite(min=0.0, max=1.0), default=0.0, show_default=True,
              help="... and moved by this share of their size, each in its own direction")
@click.option("--quiet", is_flag=True, help="no line per defect")
def eval_depth_command(sequences, recipe, backend, overrides, out, figure, device, threads, boxes, box_scale,
                       box_shift, quiet):
    """The engine's stereo and depth on labelled SEQUENCES (folders of `inspect sim generate`) with the
    true boxes: distance and deviation errors (median, p90, max), measured ÷ true, the physical floor,
    where the error lies (the ring, the region's estimate, the region's extent; from the sequence's true
    disparity), the calibration of the reported uncertainty and the decisions at the recipe's rules, for the
    recipe's depth method and for the backend's disparity alone, per sequence and, for the method, per class of
    the labels; and how many frames the check of a part without defects would say show the plate outside the
    working distance. Saves JSON, Markdown and a figure.

    --box-scale and --box-shift measure in boxes that are off as a detector's are; --boxes detector in the
    boxes of the recipe's detector that match the labels, and counts the labelled defects it missed. The
    floor stays the true box's."""
    from core import depth_eval as ev
    from core.commands.inspection import _load, distinct_folders, fail, replay_of
    from core.depth import warm_up
    from core.engine import SetupError, StageFailed, command_threads, make_plugin, plugin_context
    from core.registry import default_registry
    from core.uncertainty_budget import kind_name
    from drivers.sequence_folder import SequenceError, labelled_sequence_problem, read_labels

    overrides = list(overrides)
    if backend is not None:
        overrides += [f"stereo.backend={backend}", "stereo.settings={}"]
    if boxes == "detector" and (box_scale != 1.0 or box_shift):
        fail("--box-scale and --box-shift change the true boxes; with --boxes detector the detector draws them")
    distinct_folders(sequences, "a sequence folder")
    for folder in sequences:
        problem = labelled_sequence_problem(folder)  # it names the file
        if problem is not None:
            fail(problem)
    loaded = _load(recipe, tuple(overrides), {"stereo.backend": "--backend", "stereo.settings": "--backend"})
    command_threads(threads)
    registry = default_registry()
    ctx = plugin_context(loaded, device)
    try:
        stereo = make_plugin(loaded, registry, ctx, "stereo", loaded.recipe.stereo.backend, "stereo",
                             loaded.plugin_settings["stereo"])
    except SetupError as exc:
        fail(str(exc))
    warm_up()  # the compiled kernels loaded before the first defect: its time would count them
    rows, timings = [], []
    unscored = 0  # labelled defects whose truth has no distance or deviation
    plate_check = {"frames": 0, "flagged": []}  # each frame's plate check, as if the detector found nothing
    box_error = ev.BoxError(box_scale, box_shift)
    detector = None
    if boxes == "detector":
        from core.engine import build_detector

        try:
            detector = build_detector(loaded, registry, ctx)
        except SetupError as exc:
            fail(str(exc))
    for folder in sequences:
        camera = replay_of(folder, registry, ctx)
        for frame in camera.frames():
            if not hasattr(frame, "left"):
                fail(f"{folder}: {frame.said}")
            if "labels" not in frame.meta:
                fail(f"{folder}: frame {frame.frame_id} has no labels/{frame.frame_id}.json (the truth to compare with)")
            try:
                labels = read_labels(frame.meta["labels"], frame.left.shape[:2])
            except SequenceError as exc:
                fail(str(exc))
            unscored += sum(1 for d in labels["defects"] if not ev.has_truth(d))
            plate_check["frames"] += 1
            said = ev.plate_check(frame, loaded.recipe)
            if said is not None:
                plate_check["flagged"].append({"sequence": folder.name, "frame_id": frame.frame_id, **said})
            try:
                new = ev.evaluate_frame(frame, labels, loaded, stereo, folder.name, timings, box_error, detector)
            except StageFailed as exc:
                fail(f"{folder}: {exc}")
            except SequenceError as exc:  # a true disparity that cannot be read
                fail(str(exc))
            rows += new
            if not quiet:
                for r in new:
                    dev = "n/a" if r.deviation_mm is None else f"{r.deviation_mm:+.3f}±{r.deviation_sigma_mm or 0:.3f}"
                    z = "   n/a" if r.true_distance_mm is None else f"{r.true_distance_mm:6.1f}"
                    # a measurement no rule could decide says what its uncertainty was mostly made of
                    why = (f", undecided: mostly {kind_name(r.uncertainty_from)}"
                           if r.proven == "undecided" and r.uncertainty_from else "")
                    click.echo(f"{folder.name} {r.frame_id} {r.cls:<16} Z {z} true {r.true_deviation_mm:+.3f} "
                               f"measured {dev} mm ({r.status}{why}; disparity alone "
                               f"{'n/a' if r.reference_deviation_mm is None else f'{r.reference_deviation_mm:+.3f}'}, "
                               f"{r.reference_status}){'  ' + r.note if r.note else ''}")
    if not rows:
        fail("no labelled defect with a true deviation in " + ", ".join(str(s) for s in sequences))
    import torch

    from core.bench import machine

    m = machine()
    meta = {"recipe": str(loaded.path.name), "backend": loaded.recipe.stereo.backend,
            "settings": loaded.plugin_settings["stereo"], "method": loaded.recipe.depth.method,
            "uncertain": loaded.recipe.decision.uncertain, "coverage_factor": loaded.recipe.decision.coverage_factor,
            "machine": f"{m['cpu']}, {m['cores']} cores, {torch.get_num_threads()} torch threads"
                       + (f", GPU {m['gpu']}" if "gpu" in m and ctx.device.startswith("cuda") else ""),
            "python": platform.python_version(), "box_scale": box_scale, "box_shift": box_shift, "boxes": boxes,
            "detector": loaded.recipe.detector.plugin, "confidence": loaded.recipe.detector.confidence,
            "unscored": unscored, "plate_check": plate_check}
    per_defect = [sum(t) / len(timings) for t in zip(*timings)] if timings else [None, None]
    body = ev.report(rows, meta, *per_defect)
    written = ev.save(body, rows, out, figure)
    click.echo("")
    click.echo(ev.markdown(body))
    click.echo("wrote " + ", ".join(str(p) for p in written))


def register(cli: click.Group) -> None:
    cli.commands["eval"].add_command(eval_depth_command, "depth")
