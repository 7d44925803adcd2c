"""Axis-aligned boxes (x0, y0, x1, y1) in pixels: how much two sets of them overlap, and which match."""
from __future__ import annotations

import numpy as np

MATCH_IOU = 0.3  # a detector's box overlapping a labelled defect this much is its box of that defect


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of every box in a (N,4) with every box in b (M,4); boxes are x0, y0, x1, y1."""
    x0 = np.maximum(a[:, None, 0], b[None, :, 0])
    y0 = np.maximum(a[:, None, 1], b[None, :, 1])
    x1 = np.minimum(a[:, None, 2], b[None, :, 2])
    y1 = np.minimum(a[:, None, 3], b[None, :, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-9)


def match_boxes(truth: np.ndarray, found: np.ndarray, min_iou: float) -> list[int | None]:
    """For each of the (N, 4) ``truth`` boxes, the index of the (M, 4) ``found`` box it is matched with,
    or None: pairs are taken by falling IoU, each box at most once, none below ``min_iou``."""
    matched: list[int | None] = [None] * len(truth)
    if len(truth) == 0 or len(found) == 0:
        return matched
    iou = box_iou(np.asarray(truth, float).reshape(-1, 4), np.asarray(found, float).reshape(-1, 4))
    taken = set()
    for flat in np.argsort(-iou, axis=None, kind="stable"):
        i, j = divmod(int(flat), iou.shape[1])
        if iou[i, j] < min_iou:
            break
        if matched[i] is None and j not in taken:
            matched[i] = j
            taken.add(j)
    return matched
