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


# where a detector's boxes lie off their defects by no more than this share of their size, the depth figures hold
# (docs/depth-conditions.md, boxes that are off); a third off, a few clear-cut defects were proven inside their limit
HELD_SHIFT = 0.1
UNSAFE_SHIFT = 1 / 3


def box_placement(truth: np.ndarray, found: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How each of the (N, 4) ``found`` boxes lies against its (N, 4) ``truth`` box, in the measures of ``inspect
    eval depth --box-shift`` and ``--box-scale``: (shift (N,), the centre's offset as a share of the true box's
    width and height, ``hypot(dx / w, dy / h)``; scale (N,), the found box's size over the true one's, the square
    root of their areas' ratio)."""
    truth, found = np.asarray(truth, float).reshape(-1, 4), np.asarray(found, float).reshape(-1, 4)
    if truth.shape != found.shape:
        raise ValueError(f"box_placement: truth {truth.shape} and found {found.shape} must pair up")
    w, h = truth[:, 2] - truth[:, 0], truth[:, 3] - truth[:, 1]
    if np.any(w <= 0) or np.any(h <= 0):
        raise ValueError("box_placement: every true box needs a width and a height")
    dx = (found[:, 0] + found[:, 2] - truth[:, 0] - truth[:, 2]) / 2
    dy = (found[:, 1] + found[:, 3] - truth[:, 1] - truth[:, 3]) / 2
    area = np.clip(found[:, 2] - found[:, 0], 0, None) * np.clip(found[:, 3] - found[:, 1], 0, None)
    return np.hypot(dx / w, dy / h), np.sqrt(area / (w * h))


def matched_placement(truth: np.ndarray, found: np.ndarray, min_iou: float) -> list[tuple[int, float, float]]:
    """``box_placement`` of each (N, 4) ``truth`` box that ``match_boxes`` pairs with one of the (M, 4) ``found``:
    (the truth's index, shift, scale) for each, in the truths' order."""
    truth, found = np.asarray(truth, float).reshape(-1, 4), np.asarray(found, float).reshape(-1, 4)
    pairs = [(i, j) for i, j in enumerate(match_boxes(truth, found, min_iou)) if j is not None]
    if not pairs:
        return []
    shift, scale = box_placement(truth[[i for i, _ in pairs]], found[[j for _, j in pairs]])
    return [(i, float(a), float(b)) for (i, _), a, b in zip(pairs, shift, scale)]


def shifts_beyond(shifts) -> tuple[int, int]:
    """How many of ``shifts`` (``box_placement``'s) lie more than HELD_SHIFT and more than UNSAFE_SHIFT off."""
    shifts = np.asarray(list(shifts), float)
    return int(np.sum(shifts > HELD_SHIFT)), int(np.sum(shifts > UNSAFE_SHIFT))
