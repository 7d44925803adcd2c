"""Defect-free tiles of rendered plates as background (negative) training images.

NEU-DET holds only images with defects, so a model trained on it alone has never been told
that plain rolled steel, a plate edge or the belt is *not* a defect; on a full frame it
boxes plate texture as ``pitted_surface``. ultralytics treats an image with an empty label
file as background. These helpers cut a rendered sequence (``inspect sim generate``) into
the same tiles the detector sees at inference and keep the tiles that stay clear of every
labelled defect.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers.file_writes import write_text
from drivers.sequence_folder import write_image
from plugins.yolov8.frame_eval import check_frame_boxes, read_frame_labels, read_left
from plugins.yolov8.tiling import tile_origins


class BackgroundError(Exception):
    """The sequence or the dataset folder cannot be used; the message names the file."""


def _left(sequence: Path, frame_id: str) -> np.ndarray:
    try:
        return read_left(sequence, frame_id)
    except ValueError as exc:
        raise BackgroundError(str(exc)) from None


def clear_tiles(
    height: int, width: int, boxes: np.ndarray, tile: int, overlap: float, margin: float
) -> list[tuple[int, int]]:
    """Origins (x0, y0) of the inference tiles of a (height, width) frame that do not touch any box.

    boxes: (N, 4) x0, y0, x1, y1 in frame pixels; each box is grown by ``margin`` px first, so
    that a defect's blended rim never lands in a "background" tile.
    """
    grown = np.asarray(boxes, dtype=np.float64).reshape(-1, 4) + np.array([-margin, -margin, margin, margin])
    clear = []
    for y0 in tile_origins(height, tile, overlap):
        for x0 in tile_origins(width, tile, overlap):
            x1, y1 = x0 + tile, y0 + tile
            hit = (grown[:, 0] < x1) & (grown[:, 2] > x0) & (grown[:, 1] < y1) & (grown[:, 3] > y0)
            if not hit.any():
                clear.append((x0, y0))
    return clear


@dataclass
class BackgroundReport:
    frames: int = 0
    tiles: int = 0
    skipped_tiles: int = 0


def _frames(sequence: Path, all_clear: bool) -> list[tuple[str, np.ndarray, tuple[Path, dict] | None]]:
    """(frame id, defect boxes, its labels file and labels) of every frame: from labels/*.json, or every left image
    with none (and no labels)."""
    if all_clear:
        frames = [(p.stem, np.zeros((0, 4)), None) for p in sorted((sequence / "left").glob("*")) if p.is_file()]
        if not frames:
            raise BackgroundError(f"{sequence / 'left'}: no images")
        return frames
    if not any((sequence / "labels").glob("*.json")):
        raise BackgroundError(f"{sequence / 'labels'}: no frame labels (render one with `inspect sim generate`, "
                              "or pass --all-clear for recorded parts known to be sound)")
    try:
        labelled = read_frame_labels(sequence)
    except ValueError as exc:
        raise BackgroundError(str(exc)) from exc
    return [(frame_id, np.array([d["box"] for d in label["defects"]], dtype=np.float64).reshape(-1, 4), (path, label))
            for path, frame_id, label in labelled]


def add_backgrounds(sequence: Path, dataset: Path, split: str = "train", tile: int = 224,
                    overlap: float = 0.25, margin: float = 32.0, all_clear: bool = False) -> BackgroundReport:
    """Write every clear tile of SEQUENCE's left images into DATASET/images/SPLIT with an empty label file.

    ``all_clear``: the sequence has no labels because every part in it is sound (e.g. recorded on the
    line with ``inspect camera record``); every tile is background."""
    images_dir, labels_dir = dataset / "images" / split, dataset / "labels" / split
    if not images_dir.is_dir():
        raise BackgroundError(f"{images_dir}: not a YOLO dataset split (run `inspect data convert-voc` first)")
    frames = _frames(sequence, all_clear)
    for frame_id, _, labelled in frames:  # every image read once before any is added: a broken one adds nothing
        shape = _left(sequence, frame_id).shape[:2]
        if labelled is not None:
            # a box off its image leaves its defect unmasked: its tiles would teach the detector it is plate
            try:
                check_frame_boxes(*labelled, shape)
            except ValueError as exc:
                raise BackgroundError(str(exc)) from None
    labels_dir.mkdir(parents=True, exist_ok=True)
    report = BackgroundReport()
    written: list[Path] = []
    try:
        for frame_id, boxes, _ in frames:
            image = _left(sequence, frame_id)
            h, w = image.shape[:2]
            origins = clear_tiles(h, w, boxes, tile, overlap, margin)
            report.frames += 1
            report.skipped_tiles += len(tile_origins(h, tile, overlap)) * len(tile_origins(w, tile, overlap)) - len(origins)
            for x0, y0 in origins:
                # the sequence folder's name keeps tiles of different renders apart
                stem = f"bg_{sequence.name}_{frame_id}_{x0}_{y0}"
                tile_path, label_path = images_dir / f"{stem}.jpg", labels_dir / f"{stem}.txt"
                written += [tile_path, label_path]
                write_image(tile_path, image[y0:y0 + tile, x0:x0 + tile], (cv2.IMWRITE_JPEG_QUALITY, 95))
                write_text(label_path, "")
                report.tiles += 1
    except OSError as exc:
        # half a sequence's tiles would train the detector on whichever frames came first
        for path in written:
            path.unlink(missing_ok=True)
        raise BackgroundError(f"{exc}; the {report.tiles} tiles added before it were removed again") from None
    # ultralytics caches the label scan per split; a stale cache would hide the new images
    (dataset / "labels" / f"{split}.cache").unlink(missing_ok=True)
    return report
