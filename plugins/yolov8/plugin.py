"""Registers the ``yolov8`` detector and its commands (convert-voc, add-backgrounds, train detector, train average, eval detector, eval detector-frames)."""
from __future__ import annotations

import sys
from pathlib import Path

import click

from core.boxes import MATCH_IOU
from core.commands.params import Finite, out_file, out_folder, overwritten_input
from core.contracts import PluginContext, PluginSpec
from core.hookspecs import hookimpl
from plugins.yolov8.detector import (DEFAULT_WEIGHTS, WHOLE_FRAME_MAX_IMGSZ, DetectionLimit, YoloDetector,
                                     YoloSettings, checkpoint_class_names, read_checkpoint)


def _factory(settings: dict, ctx: PluginContext) -> YoloDetector:
    return YoloDetector(YoloSettings(**settings), device=ctx.device)


def _class_names(settings: dict, ctx: PluginContext) -> list[str]:
    s = YoloSettings(**settings)
    return checkpoint_class_names(Path(s.weights) if s.weights else DEFAULT_WEIGHTS, s.trust_pickle)


def _warnings(settings: dict, ctx: PluginContext) -> list[tuple[str, str]]:
    """A network input under half the size the model was trained at: its defects shrink below any it learnt (the
    demo's model at 32 px found none of the demo's seven, every part passed), or tiles that small cut them (at
    32 px tiles, 3 of the 7 passed)."""
    s = YoloSettings(**settings)
    # the network's input: imgsz, or the tile itself where imgsz is null (the whole frame's is not known here)
    key, size = ("imgsz", s.imgsz) if s.imgsz is not None else ("tile_size", s.tile_size)
    if size is None:
        return []
    ckpt = read_checkpoint(Path(s.weights) if s.weights else DEFAULT_WEIGHTS, s.trust_pickle)
    trained = (ckpt.get("train_args") or {}).get("imgsz")
    if not isinstance(trained, int) or size >= trained / 2:
        return []
    return [(key, f"{size} px of network input, under half the {trained} px the model was trained at: a defect "
                  f"shrinks below the sizes it learnt, or is cut by the tiles, may not be found, and its part then "
                  f"passes")]


@hookimpl
def stereo_inspect_detectors() -> list[PluginSpec]:
    return [
        PluginSpec(
            name="yolov8",
            kind="detector",
            factory=_factory,
            settings_model=YoloSettings,
            description="ultralytics YOLOv8 (NEU-DET weights by default), tiled inference",
            class_names=_class_names,
            warnings=_warnings,
        )
    ]


def _fail(message: str) -> None:
    click.echo(f"error: {message}", err=True)
    sys.exit(2)


def _dataset_yaml(data: Path, splits: tuple[str, ...], hint: str = "") -> Path:
    """The dataset's data.yaml (``data`` or the one inside it), checked for what ultralytics needs; otherwise
    one line naming it (ultralytics would raise with a traceback)."""
    import yaml

    from drivers.yaml_reader import Misread, safe_load

    data_yaml = data / "data.yaml" if data.is_dir() else data
    if not data_yaml.is_file():
        _fail(f"{data_yaml}: dataset file not found{hint}")
    try:
        spec = safe_load(data_yaml.read_text(encoding="utf-8-sig"))
    except Misread as exc:
        _fail(f"{data_yaml}:{exc.line}: {exc.described}")
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        _fail(f"{data_yaml}: not a dataset description ({str(exc).splitlines()[0]})")
    missing = [k for k in (*splits, "names") if not isinstance(spec, dict) or k not in spec]
    if missing:
        _fail(f"{data_yaml}: not a YOLO dataset description: no {', '.join(missing)}{hint}")
    return data_yaml


@click.command("convert-voc")
@click.argument("src", type=click.Path(path_type=Path))
@click.argument("dst", type=click.Path(path_type=Path))
@click.option("--split-files", nargs=2, type=click.Path(path_type=Path), default=None,
              help="train and val stem lists (e.g. train.txt val.txt); relative to SRC when not found as given; "
                   "default: SRC's train.txt and val.txt where it has both")
def convert_voc_command(src: Path, dst: Path, split_files: tuple[Path, Path] | None) -> None:
    """Convert a Pascal VOC folder (images/, annotations/) into the YOLO layout with data.yaml.

    Without split files (given, or SRC's train.txt and val.txt) every image is in train and val is the same
    images, which is said: scores on it are scores on the training images."""
    from drivers.sequence_folder import SequenceError
    from plugins.yolov8.voc_to_yolo import convert_voc

    if not (src / "images").is_dir() or not (src / "annotations").is_dir():
        _fail(f"{src}: expected images/ and annotations/ folders")
    if split_files is None and (src / "train.txt").is_file() and (src / "val.txt").is_file():
        split_files = (src / "train.txt", src / "val.txt")
        click.echo(f"splits: {split_files[0]}, {split_files[1]}")
    elif split_files is None:
        click.echo(f"warning: {src} has no train.txt and val.txt and no --split-files were given: every image is in "
                   f"train, and val is the same images, so a score on val says nothing of images the model has not "
                   f"seen", err=True)
    splits = None
    if split_files:
        splits = {}
        for name, path in zip(("train", "val"), split_files):
            path = path if path.exists() else src / path
            if not path.exists():
                _fail(f"{path}: split file not found")
            splits[name] = path
    try:
        report = convert_voc(src, dst, splits)
    except SequenceError as exc:  # a split file that is not text
        _fail(str(exc))
    for message in report.messages:
        click.echo(f"warning: {message}", err=True)
    click.echo(report.summary())
    click.echo(f"dataset: {dst / 'data.yaml'}")


@click.command("add-backgrounds")
@click.argument("sequence", type=click.Path(path_type=Path))
@click.argument("dataset", type=click.Path(path_type=Path))
@click.option("--split", default="train", show_default=True)
@click.option("--tile", default=224, show_default=True, type=click.IntRange(min=32),
              help="tile edge in frame pixels, as the recipe's tile_size")
@click.option("--overlap", default=0.25, show_default=True, type=Finite(0.0, 0.9, max_open=True),
              help="as the recipe's tile_overlap")
@click.option("--margin", default=32.0, show_default=True, type=Finite(min=0.0),
              help="px kept clear around every labelled defect")
@click.option("--all-clear", is_flag=True, help="no labels: every part in SEQUENCE is sound (recorded good parts)")
def add_backgrounds_command(sequence: Path, dataset: Path, split: str, tile: int, overlap: float, margin: float,
                            all_clear: bool) -> None:
    """Add the defect-free tiles of a labelled sequence (`inspect sim generate`), or of recorded sound parts
    (`inspect camera record`, --all-clear), to DATASET as background images."""
    from plugins.yolov8.backgrounds import BackgroundError, add_backgrounds

    try:
        report = add_backgrounds(sequence, dataset, split, tile, overlap, margin, all_clear)
    except BackgroundError as exc:
        _fail(str(exc))
    click.echo(f"{report.tiles} background tiles from {report.frames} frames "
               f"({report.skipped_tiles} tiles near a defect left out) -> {dataset / 'images' / split}")


@click.command("detector")
@click.option("--data", "data", required=True, type=click.Path(path_type=Path), help="YOLO dataset folder or its data.yaml")
@click.option("--epochs", default=100, show_default=True, type=click.IntRange(min=1))
@click.option("--patience", default=20, show_default=True, type=click.IntRange(min=0))
@click.option("--imgsz", default=200, show_default=True, type=click.IntRange(32, 4096))
@click.option("--batch", default=16, show_default=True, type=click.IntRange(min=1))
@click.option("--device", default="auto", show_default=True)
@click.option("--out", default=Path("runs/detector"), type=click.Path(path_type=Path), show_default=True)
@click.option("--workers", default=2, show_default=True, type=click.IntRange(min=0), help="data-loader processes")
@click.option("--name", default="yolov8n-neu", show_default=True)
@click.option("--init", "init", default=None, type=click.Path(path_type=Path),
              help="start from these weights (an earlier run of ours, never a downloaded checkpoint) with a fresh schedule")
@click.option("--optimizer", default="auto", show_default=True,
              type=click.Choice(["auto", "SGD", "Adam", "Adamax", "AdamW", "NAdam", "RAdam", "RMSProp"]),
              help="SGD, AdamW, ...; 'auto' lets ultralytics choose the optimiser and its learning rate (lr0 unused)")
@click.option("--lr0", default=0.01, show_default=True, type=Finite(0.0, min_open=True),
              help="initial learning rate (with a named --optimizer)")
@click.option("--lrf", default=0.01, show_default=True, type=Finite(0.0, 1.0, min_open=True),
              help="final learning rate as a fraction of lr0 (linear decay)")
@click.option("--warmup-epochs", default=3.0, show_default=True, type=Finite(min=0.0))
@click.option("--save-period", default=-1, show_default=True, type=click.IntRange(min=-1),
              help="also keep the weights of every Nth epoch (for `inspect train average`); -1: only best and last")
def train_command(data: Path, epochs: int, patience: int, imgsz: int, batch: int, device: str, out: Path,
                  workers: int, name: str, init: Path | None, optimizer: str, lr0: float, lrf: float,
                  warmup_epochs: float, save_period: int) -> None:
    """Train YOLOv8n from scratch (resumes when OUT/NAME/weights/last.pt exists)."""
    from plugins.yolov8.training import TrainSettings, last_checkpoint, train_detector

    data_yaml = _dataset_yaml(data, ("train", "val"), " (run `inspect data convert-voc` first)")
    from plugins.yolov8.dataset_check import dataset_problem
    from plugins.yolov8.detector import read_checkpoint

    problem = dataset_problem(data_yaml, ("train", "val"))
    if problem is not None:
        _fail(problem)

    last = last_checkpoint(out, name)
    for option, weights in (("--init", init), ("resuming from", last if last.exists() else None)):
        if weights is not None:
            try:
                read_checkpoint(weights, hint=None)  # ultralytics' own loader would run whatever the pickle calls
            except (OSError, ValueError) as exc:
                _fail(f"{option} {exc}")
    settings = TrainSettings(epochs=epochs, patience=patience, imgsz=imgsz, batch=batch, device=device, workers=workers,
                             optimizer=optimizer, lr0=lr0, lrf=lrf, warmup_epochs=warmup_epochs,
                             save_period=save_period)
    best = train_detector(data_yaml, out, settings, name, init=init)
    click.echo(f"best weights: {best}")


@click.command("average")
@click.argument("weights", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--out", required=True, type=click.Path(path_type=Path), callback=out_file,
              help="the averaged checkpoint to write")
def average_command(weights: tuple[Path, ...], out: Path) -> None:
    """Average the weights of several detector checkpoints of one architecture (a model soup)."""
    from plugins.yolov8.averaging import AveragingError, average_checkpoints

    if len(weights) < 2:
        _fail("give at least two checkpoints to average")
    for path in weights:
        if not path.is_file():
            _fail(f"{path}: weights file not found")
    seen: dict[Path, Path] = {}
    for path in weights:
        first = seen.get(path.resolve())
        if first is not None:  # a repeated glob: the mean would weigh that checkpoint twice
            _fail(f"{path}: given twice" + ("" if str(first) == str(path) else f" (as {first} too)"))
        seen[path.resolve()] = path
    overwrite = overwritten_input({"--out": out}, list(weights))
    if overwrite is not None:
        _fail(overwrite)
    try:
        average_checkpoints(list(weights), out)
    except AveragingError as exc:
        _fail(str(exc))
    click.echo(f"mean of {len(weights)} checkpoints -> {out}")


@click.command("detector")
@click.option("--data", "data", required=True, type=click.Path(path_type=Path))
@click.option("--weights", required=True, type=click.Path(path_type=Path))
@click.option("--split", default="val", show_default=True)
@click.option("--imgsz", default=224, show_default=True, type=click.IntRange(32, 4096))
@click.option("--iou", default=YoloSettings.model_fields["iou"].default, show_default=True, type=Finite(0, 1, min_open=True),
              help="NMS IoU; the default is what the yolov8 detector runs with (detector.settings.iou); ultralytics' own val uses 0.7")
@click.option("--out", default=Path("runs/detector-eval"), type=click.Path(path_type=Path), show_default=True,
              callback=out_folder)
def eval_command(data: Path, weights: Path, split: str, imgsz: int, iou: float, out: Path) -> None:
    """mAP@0.50, mAP@0.50:0.95, precision, recall and per-class AP, beside the seed's figures.

    A dataset whose classes are not the model's (in its order), or with an image or label line ultralytics
    would drop, is refused naming the file."""
    from plugins.yolov8.dataset_check import dataset_problem, resolved, shared_with_train
    from plugins.yolov8.detector import checkpoint_class_names
    from plugins.yolov8.evaluation import evaluate_detector, metrics_markdown

    data_yaml = _dataset_yaml(data, (split,))
    if not weights.is_file():
        _fail(f"{weights}: weights file not found")
    try:
        info = resolved(data_yaml)
        problem = dataset_problem(data_yaml, (split,), checkpoint_class_names(weights), info)
        if problem is not None:
            _fail(problem)
        shared = shared_with_train(info, split)
        if shared:
            click.echo(f"warning: {data_yaml}: {shared} of the {split} images are also train images: a score on them "
                       f"says how well the model learnt them, not how it finds defects it has not seen", err=True)
        result = evaluate_detector(data_yaml, weights, split, out, imgsz=imgsz, iou=iou)
    except ValueError as exc:
        _fail(str(exc))
    click.echo(metrics_markdown(result))
    click.echo(f"saved: {out / 'detector_metrics.json'}, {out / 'detector_metrics.md'}, {out / 'pr_curve.png'}")


@click.command("detector-frames")
@click.argument("sequence", type=click.Path(path_type=Path), default=Path("sim_fixtures/steel_plate"))
@click.option("--weights", default=None, type=click.Path(path_type=Path), help="default: the committed model")
@click.option("--confidence", "confidences", default="0.05,0.1,0.2,0.3,0.4,0.5", show_default=True,
              help="comma-separated thresholds to score")
@click.option("--tile-size", default=224, show_default=True, type=click.IntRange(min=0),
              help="0: the whole frame in one piece; else at least 32")
@click.option("--tile-overlap", default=0.25, show_default=True, type=Finite(0.0, 0.9, max_open=True))
@click.option("--imgsz", type=click.IntRange(32, 4096), default=None, help="network input size; default: the tile's "
              f"size, or the frame's long side up to {WHOLE_FRAME_MAX_IMGSZ} px (a larger frame shrunk to it)")
@click.option("--iou", default=MATCH_IOU, show_default=True, type=Finite(0.0, 1.0, min_open=True),
              help="a box this close to a labelled defect finds it")
def eval_frames_command(sequence: Path, weights: Path | None, confidences: str, tile_size: int, tile_overlap: float,
                        imgsz: int | None, iou: float) -> None:
    """The detector on whole frames of a labelled sequence, tiled as on the line: defects found, boxes on sound
    surface, and how far its boxes lie off their defects (depth is measured in them)."""
    from plugins.yolov8.frame_eval import load_labelled_frames, markdown, score_frames

    try:
        thresholds = sorted(float(c) for c in confidences.split(","))
    except ValueError:
        _fail(f"--confidence: {confidences!r} is not a comma-separated list of numbers")
    if not all(0.0 <= t <= 1.0 for t in thresholds):
        _fail(f"--confidence: {confidences!r}: each threshold is a number from 0 to 1")
    if 0 < tile_size < 32:
        _fail(f"--tile-size {tile_size}: 0 (the whole frame) or at least 32")
    if weights is not None and not weights.is_file():
        _fail(f"{weights}: weights file not found")
    try:
        frames = load_labelled_frames(sequence)
    except ValueError as exc:
        _fail(str(exc))
    try:
        # ultralytics' own max_det: low thresholds find more boxes than the line's 100
        detector = YoloDetector(YoloSettings(weights=str(weights) if weights else None, confidence=min(thresholds),
                                             tile_size=tile_size or None, tile_overlap=tile_overlap, imgsz=imgsz,
                                             max_det=300), device="cpu")
    except ValueError as exc:  # not a checkpoint, or one that would run code (its message names the file)
        _fail(" ".join(str(exc).split()))
    detections = []
    for frame_id, image, _ in frames:
        try:
            detections.append([(d.class_name, d.confidence, d.box) for d in detector.detect(image)])
        except DetectionLimit:  # boxes beyond max_det would go uncounted as boxes on sound surface
            _fail(f"{sequence}: frame {frame_id}: at --confidence {min(thresholds):g} the detector finds "
                  f"{detector.settings.max_det} boxes or more in one image, more than it reports: score higher "
                  f"thresholds")
    click.echo(f"{sequence}: {len(frames)} frames, weights {weights or 'the committed model'}")
    click.echo(markdown(score_frames(detections, [t for _, _, t in frames], thresholds, iou)))


@hookimpl
def stereo_inspect_commands(cli: click.Group) -> None:
    cli.commands["data"].add_command(convert_voc_command)
    cli.commands["data"].add_command(add_backgrounds_command)
    cli.commands["train"].add_command(train_command)
    cli.commands["train"].add_command(average_command)
    cli.commands["eval"].add_command(eval_command)
    cli.commands["eval"].add_command(eval_frames_command)
