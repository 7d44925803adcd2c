"""Sliced inference helpers: where tiles go and how boxes cut by tile borders are merged back.

NEU-DET images are 200x200 crops in which a defect fills a good share of the image; on a full
camera frame the same defect is small, so the frame is cut into tiles of about the training
scale, each tile is detected on its own, and the results are merged.
"""
from __future__ import annotations

import numpy as np

from core.boxes import box_iou


def tile_origins(length: int, tile: int, overlap: float) -> list[int]:
    """Start offsets covering ``[0, length)`` with tiles of ``tile`` px overlapping by ``overlap`` (0..<1)."""
    if length <= tile:
        return [0]
    step = max(1, int(round(tile * (1.0 - overlap))))
    origins = list(range(0, length - tile, step))
    origins.append(length - tile)
    return sorted(set(origins))


def nms(boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, iou: float) -> np.ndarray:
    """Indices kept by class-aware non-maximum suppression, best score first."""
    keep: list[int] = []
    order = np.argsort(-scores)
    suppressed = np.zeros(len(boxes), dtype=bool)
    overlaps = box_iou(boxes, boxes)
    for i in order:
        if suppressed[i]:
            continue
        keep.append(int(i))
        suppressed |= (overlaps[i] > iou) & (classes == classes[i])
    return np.array(keep, dtype=int)


def _touches_cut(box: np.ndarray, cuts_x: list[int], cuts_y: list[int], tol: float) -> bool:
    return any(abs(box[0] - c) <= tol or abs(box[2] - c) <= tol for c in cuts_x) or any(
        abs(box[1] - c) <= tol or abs(box[3] - c) <= tol for c in cuts_y
    )


def merge_cut_boxes(
    boxes: np.ndarray, scores: np.ndarray, classes: np.ndarray, cuts_x: list[int], cuts_y: list[int],
    tol: float = 3.0, max_size: float = float("inf"),
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Join same-class boxes that overlap or touch where one of them ends at a tile border.

    ``cuts_x``/``cuts_y`` are the interior tile edges (where a tile starts or ends inside the
    image); a box ending there was probably cut by the tile, not by the defect. No join grows a
    box beyond ``max_size`` in either direction: detections that fill whole tiles (a texture
    class seen everywhere) would otherwise chain into one box the size of the frame.
    """
    boxes, scores, classes = boxes.copy(), scores.copy(), classes.copy()
    merged = True
    while merged and len(boxes) > 1:
        merged = False
        for i in range(len(boxes)):
            for j in range(i + 1, len(boxes)):
                if classes[i] != classes[j]:
                    continue
                a, b = boxes[i], boxes[j]
                gap_x = max(a[0], b[0]) - min(a[2], b[2])
                gap_y = max(a[1], b[1]) - min(a[3], b[3])
                if gap_x > tol or gap_y > tol:
                    continue
                if not (_touches_cut(a, cuts_x, cuts_y, tol) or _touches_cut(b, cuts_x, cuts_y, tol)):
                    continue
                union = [min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3])]
                if union[2] - union[0] > max_size or union[3] - union[1] > max_size:
                    continue
                boxes[i] = union
                scores[i] = max(scores[i], scores[j])
                boxes = np.delete(boxes, j, axis=0)
                scores = np.delete(scores, j)
                classes = np.delete(classes, j)
                merged = True
                break
            if merged:
                break
    return boxes, scores, classes


def interior_cuts(origins: list[int], tile: int, length: int) -> list[int]:
    cuts = {o for o in origins if 0 < o < length} | {o + tile for o in origins if 0 < o + tile < length}
    return sorted(cuts)
