"""``core.boxes``: overlaps of boxes and which labelled box a detector's box found."""
from __future__ import annotations

import numpy as np
import pytest

from core.boxes import box_iou, box_placement, match_boxes, matched_placement, shifts_beyond


class TestBoxIou:
    def test_identical_disjoint_and_half_overlapping_boxes(self):
        a = np.array([[0, 0, 10, 10]], float)
        b = np.array([[0, 0, 10, 10], [20, 20, 30, 30], [5, 0, 15, 10]], float)
        assert box_iou(a, b)[0] == pytest.approx([1.0, 0.0, 50 / 150])


class TestMatchBoxes:
    def test_each_truth_takes_its_best_box_and_no_box_serves_two(self):
        truth = np.array([[0, 0, 10, 10], [1, 0, 11, 10]], float)
        found = np.array([[1, 0, 11, 10], [50, 50, 60, 60]], float)
        # both truths overlap the first box most; the second truth's overlap is the higher, so it takes it
        assert match_boxes(truth, found, 0.3) == [None, 0]

    def test_pairs_are_taken_by_falling_overlap(self):
        truth = np.array([[0, 0, 10, 10], [8, 0, 18, 10]], float)
        found = np.array([[7, 0, 17, 10], [0, 0, 9, 10]], float)
        assert match_boxes(truth, found, 0.3) == [1, 0]

    def test_an_overlap_below_the_threshold_is_no_match(self):
        truth = np.array([[0, 0, 10, 10]], float)
        assert match_boxes(truth, np.array([[6, 0, 16, 10]], float), 0.3) == [None]  # IoU 0.25
        assert match_boxes(truth, np.array([[6, 0, 16, 10]], float), 0.2) == [0]

    def test_nothing_found_or_nothing_to_find(self):
        assert match_boxes(np.array([[0, 0, 1, 1]], float), np.zeros((0, 4)), 0.3) == [None]
        assert match_boxes(np.zeros((0, 4)), np.array([[0, 0, 1, 1]], float), 0.3) == []


class TestBoxPlacement:
    def test_a_box_moved_and_scaled_as_eval_depth_moves_them(self):
        truth = np.array([[0, 0, 20, 10], [0, 0, 20, 10], [100, 50, 140, 70]], float)
        # a tenth of its width along; 6 px along and 4 down; the same centre, 1.5 times as large
        found = np.array([[2, 0, 22, 10], [6, 4, 26, 14], [90, 45, 150, 75]], float)
        shift, scale = box_placement(truth, found)
        assert shift == pytest.approx([0.1, np.hypot(6 / 20, 4 / 10), 0.0])
        assert scale == pytest.approx([1.0, 1.0, 1.5])

    def test_shapes_must_pair_and_true_boxes_have_a_size(self):
        with pytest.raises(ValueError, match="must pair up"):
            box_placement(np.zeros((2, 4)), np.zeros((1, 4)))
        with pytest.raises(ValueError, match="width and a height"):
            box_placement(np.array([[5, 5, 5, 9]], float), np.array([[5, 5, 6, 9]], float))
        shift, scale = box_placement(np.zeros((0, 4)), np.zeros((0, 4)))
        assert shift.shape == scale.shape == (0,)


class TestMatchedPlacement:
    def test_each_matched_truth_with_its_boxs_placement(self):
        truth = np.array([[0, 0, 20, 10], [100, 0, 120, 10], [300, 0, 320, 10]], float)
        found = np.array([[104, 0, 124, 10], [2, 0, 22, 10]], float)  # the third truth has none
        assert matched_placement(truth, found, 0.3) == [(0, pytest.approx(0.1), pytest.approx(1.0)),
                                                        (1, pytest.approx(0.2), pytest.approx(1.0))]
        assert matched_placement(truth, np.zeros((0, 4)), 0.3) == []


class TestShiftsBeyond:
    def test_a_tenth_and_a_third_are_inside_their_own_bound(self):
        assert shifts_beyond([0.05, 0.1, 0.2, 1 / 3, 0.5]) == (3, 1)
        assert shifts_beyond([]) == (0, 0)
