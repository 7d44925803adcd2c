"""The detector as the line uses it: tiled inference on whole frames of a labelled sequence
(``inspect sim generate`` output or any folder with ``left/`` and ``labels/*.json``).

NEU-DET's mAP is measured on 200x200 crops that each hold a defect. On the line the same model
sees whole frames, mostly plain plate and belt; what matters there is how many real defects it
finds and how many boxes it puts on sound surface, at the recipe's confidence threshold.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.sequence_folder import SequenceError, check_label_boxes, read_image, read_labels
from core.boxes import MATCH_IOU, box_iou


@dataclass
class FrameEvalRow:
    confidence: float
    defects: int  # labelled defects in the sequence
    found: int  # labelled defects overlapped by a box (IoU >= the threshold), any class
    found_same_class: int
    other_boxes: int  # boxes on no labelled defect
    frames: int

    @property
    def other_per_frame(self) -> float:
        return self.other_boxes / self.frames if self.frames else 0.0


def _read(path: Path) -> dict:
    try:
        return read_labels(path)
    except SequenceError as exc:
        raise ValueError(str(exc)) from None


def read_frame_labels(sequence: Path) -> list[tuple[Path, str, dict]]:
    """(file, frame id, labels) of every ``labels/*.json``; one-line errors name the file. Its boxes are checked
    against their image, once that is read, by ``check_frame_boxes``."""
    paths = sorted((sequence / "labels").glob("*.json"))
    if not paths:
        raise ValueError(f"{sequence / 'labels'}: no frame labels")
    # the file's own name when the labels do not say (the sequence's frames are named by it)
    return [(path, str(label.get("frame_id", path.stem)), label) for path, label in ((p, _read(p)) for p in paths)]


def check_frame_boxes(path: Path, label: dict, shape: tuple[int, int]) -> None:
    """``ValueError`` naming the labels file ``path`` where a box of ``label`` misses the HxW image of ``shape``."""
    try:
        check_label_boxes(label, shape, path)
    except SequenceError as exc:
        raise ValueError(str(exc)) from None


def read_left(sequence: Path, frame_id: str) -> np.ndarray:
    """The frame's left image; ``ValueError`` naming the file where it is missing, cut short or corrupt."""
    found = sorted((sequence / "left").glob(f"{frame_id}.*"))
    if not found:
        raise ValueError(f"{sequence / 'left' / frame_id}.*: left image missing")
    try:
        return read_image(found[0], f"left image of frame {frame_id}")
    except SequenceError as exc:
        raise ValueError(str(exc)) from None


def load_labelled_frames(sequence: Path) -> list[tuple[str, np.ndarray, list[dict]]]:
    """(frame id, left image, labelled defects) for every frame of ``sequence``, each labelled box checked
    against its image's size (one outside it would count as a defect the detector missed)."""
    frames = []
    for path, frame_id, label in read_frame_labels(sequence):
        image = read_left(sequence, frame_id)
        check_frame_boxes(path, label, image.shape[:2])
        frames.append((frame_id, image, label["defects"]))
    return frames


def score_frames(detections: list[list[tuple[str, float, tuple]]], truths: list[list[dict]],
                 confidences: list[float], iou: float = MATCH_IOU) -> list[FrameEvalRow]:
    """detections[i]: (class, confidence, box) of frame i; truths[i]: its labelled defects ({class, box})."""
    rows = []
    for conf in confidences:
        row = FrameEvalRow(conf, 0, 0, 0, 0, len(truths))
        for dets, truth in zip(detections, truths):
            kept = [d for d in dets if d[1] >= conf]
            boxes = np.array([d[2] for d in kept], dtype=np.float64).reshape(-1, 4)
            gt = np.array([t["box"] for t in truth], dtype=np.float64).reshape(-1, 4)
            row.defects += len(gt)
            if not len(boxes):
                continue
            if not len(gt):
                row.other_boxes += len(boxes)
                continue
            overlap = box_iou(gt, boxes) >= iou
            row.found += int(overlap.any(axis=1).sum())
            same = np.array([[t["class"] == d[0] for d in kept] for t in truth])
            row.found_same_class += int((overlap & same).any(axis=1).sum())
            row.other_boxes += int((~overlap.any(axis=0)).sum())
        rows.append(row)
    return rows


def markdown(rows: list[FrameEvalRow]) -> str:
    lines = ["| confidence | defects found (any class) | same class | boxes on sound surface | per frame |",
             "|---|---|---|---|---|"]
    lines += [f"| {r.confidence:.2f} | {r.found}/{r.defects} | {r.found_same_class}/{r.defects} | {r.other_boxes} | "
              f"{r.other_per_frame:.1f} |" for r in rows]
    return "\n".join(lines)
