"""The detector as the line uses it: tiled inference on whole frames of a labelled sequence
(``inspect sim generate`` output or any folder with ``left/`` and ``labels/*.json``).

NEU-DET's mAP is measured on 200x200 crops that each hold a defect. On the line the same model
sees whole frames, mostly plain plate and belt; what matters there is how many real defects it
finds and how many boxes it puts on sound surface, at the recipe's confidence threshold, and how far its boxes
lie off their defects, since depth is measured in them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivers.sequence_folder import SequenceError, check_label_boxes, read_image, read_labels
from core.boxes import MATCH_IOU, box_iou, matched_placement, shifts_beyond


@dataclass
class FrameEvalRow:
    confidence: float
    defects: int  # labelled defects in the sequence
    found: int  # labelled defects overlapped by a box (IoU >= the threshold), any class
    found_same_class: int
    other_boxes: int  # boxes on no labelled defect
    frames: int
    # each found defect's box against its labelled one (``core.boxes.box_placement``): the centre's offset as a
    # share of the defect's size, and the box's size over the defect's
    shifts: list[float] = field(default_factory=list)
    scales: list[float] = field(default_factory=list)

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
            for _, shift, scale in matched_placement(gt, boxes, iou):
                row.shifts.append(shift)
                row.scales.append(scale)
        rows.append(row)
    return rows


def markdown(rows: list[FrameEvalRow]) -> str:
    lines = ["| confidence | defects found (any class) | same class | boxes on sound surface | per frame | box centre "
             "off its defect's, median / max (share of its size) | box size ÷ the defect's, min-max | boxes off by "
             "more than a tenth (a third) |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r.confidence:.2f} | {r.found}/{r.defects} | {r.found_same_class}/{r.defects} | {r.other_boxes} | "
              f"{r.other_per_frame:.1f} | {_placement(r)} |" for r in rows]
    lines += ["", "Depth is measured in a detector's boxes: boxes within a tenth of their defect's size of its centre "
              "keep the evaluation's depth figures; a third off, a defect beyond its limit may be proven inside it "
              "(docs/depth-conditions.md, boxes that are off)."]
    return "\n".join(lines)


def _placement(row: FrameEvalRow) -> str:
    """The table's placement columns of ``row``: dashes where it matched no defect."""
    if not row.shifts:
        return "- | - | -"
    tenth, third = shifts_beyond(row.shifts)
    return (f"{np.median(row.shifts):.2f} / {max(row.shifts):.2f} | {min(row.scales):.2f}-{max(row.scales):.2f} | "
            f"{tenth} ({third}) of {len(row.shifts)}")
