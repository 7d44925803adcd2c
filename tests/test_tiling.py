from __future__ import annotations

import numpy as np

from plugins.yolov8 import tiling


def test_tiles_cover_the_image_with_overlap():
    origins = tiling.tile_origins(672, 224, 0.25)
    assert origins[0] == 0 and origins[-1] == 672 - 224
    assert all(b - a <= 224 * 0.75 + 1 for a, b in zip(origins, origins[1:]))
    assert tiling.tile_origins(200, 224, 0.25) == [0]


def test_nms_is_class_aware():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [0, 0, 10, 10]], float)
    keep = tiling.nms(boxes, np.array([0.9, 0.8, 0.7]), np.array([0, 0, 1]), 0.5)
    assert sorted(keep.tolist()) == [0, 2]


def test_box_cut_by_a_tile_border_is_joined():
    cuts_x = tiling.interior_cuts([0, 168], 224, 392)  # tiles [0,224) and [168,392)
    assert cuts_x == [168, 224]
    boxes = np.array([[150, 40, 224, 60], [222, 41, 300, 62], [350, 10, 380, 30]], float)
    merged, scores, classes = tiling.merge_cut_boxes(boxes, np.array([0.6, 0.7, 0.5]), np.array([3, 3, 3]), cuts_x, [])
    assert merged.tolist() == [[150, 40, 300, 62], [350, 10, 380, 30]]
    assert scores.tolist() == [0.7, 0.5]


def test_neighbours_not_at_a_border_stay_apart():
    boxes = np.array([[10, 10, 50, 50], [51, 10, 90, 50]], float)
    merged, _, _ = tiling.merge_cut_boxes(boxes, np.array([0.6, 0.7]), np.array([1, 1]), [168], [])
    assert len(merged) == 2


def test_whole_tile_detections_do_not_chain_across_the_frame():
    xs = tiling.tile_origins(672, 224, 0.25)
    cuts = tiling.interior_cuts(xs, 224, 672)
    boxes = np.array([[x, 0, x + 224, 224] for x in xs], float)
    merged, _, _ = tiling.merge_cut_boxes(boxes, np.full(len(xs), 0.5), np.zeros(len(xs), int), cuts, [], max_size=336)
    assert len(merged) > 1
    assert all(b[2] - b[0] <= 336 for b in merged)
