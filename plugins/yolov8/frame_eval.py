"""The detector as the line uses it: tiled inference on whole frames of a labelled sequence
(``inspect sim generate`` output or any folder with ``left/`` and ``labels/*.json``).

NEU-DET's mAP is measured on 200x200 crops that each hold a defect. On the line the same model
sees whole frames, mostly plain plate and belt; what matters there is how many real defects it
finds and how many boxes it puts on sound surface, at the recipe's confidence threshold.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from drivers.sequence_folder import SequenceError, read_labels
from core.boxes import box_iou


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


def read_frame_labels(sequence: Path, with_images: bool = False) -> list[tuple]:
    """(frame id, labelled defects) of every ``labels/*.json``, or with ``with_images`` (frame id, left
    image, labelled defects), each box checked against the image's size; one-line errors name the file."""
    labels = sorted((sequence / "labels").glob("*.json"))
    if not labels:
        raise ValueError(f"{sequence / 'labels'}: no frame labels")
    frames = []
    for path in labels:
        try:
            label = read_labels(path)
            # the file's own name when it does not say (the sequence's frames are named by it)
            frame_id = str(label.get("frame_id", path.stem))
            if not with_images:
                frames.append((frame_id, label["defects"]))
                continue
            image = read_left(sequence, frame_id)
            frames.append((frame_id, image, read_labels(path, image.shape[:2])["defects"]))
        except SequenceError as exc:
            raise ValueError(str(exc)) from None
    return frames


def read_left(sequence: Path, frame_id: str) -> np.ndarray:
    found = sorted((sequence / "left").glob(f"{frame_id}.*"))
    image = cv2.imread(str(found[0]), cv2.IMREAD_COLOR) if found else None
    if image is None:
        raise ValueError(f"{sequence / 'left' / frame_id}.*: left image missing or unreadable")
    return image


def load_labelled_frames(sequence: Path) -> list[tuple[str, np.ndarray, list[dict]]]:
    """(frame id, left image, labelled defects) for every frame of ``sequence``."""
    return read_frame_labels(sequence, with_images=True)


def score_frames(detections: list[list[tuple[str, float, tuple]]], truths: list[list[dict]],
                 confidences: list[float], iou: float = 0.3) -> list[FrameEvalRow]:
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
