"""Coarse-to-fine search (``search: coarse_to_fine``): each stage function, then the whole pipeline
against the full search on scenes with exact ground truth."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plugins.torch_sgm import search
from plugins.torch_sgm.pipeline import TorchSGMParams, bgr_to_tensor, coarse_range, compute_disparity
from plugins.torch_sgm.synthetic import Layer, fronto_parallel, layered_scene, render

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def test_downsample_averages_blocks_and_halves_a_known_disparity():
    image = torch.arange(16.0).view(1, 1, 4, 4)
    assert torch.equal(search.downsample(image, 2), torch.tensor([[[[2.5, 4.5], [10.5, 12.5]]]]))
    # a shift of 12 px at full resolution is a shift of 3 px at a quarter of it
    left, right, _, _ = fronto_parallel(96, 160, 12.0, seed=3)
    small_l = search.downsample(bgr_to_tensor(left, torch.device("cpu")), 4)
    small_r = search.downsample(bgr_to_tensor(right, torch.device("cpu")), 4)
    inner = (slice(None), slice(None), slice(4, -4), slice(8, -4))
    assert torch.allclose(small_l[..., 3:][inner], small_r[..., :-3][inner], atol=0.02)


def test_coarse_bounds_cover_the_range_and_stay_inside_the_coarse_image():
    assert search.coarse_bounds(14, 142, 4, 168) == (3, 37)
    lo, hi = search.coarse_bounds(0, 600, 4, 168)
    assert (lo, hi) == (0, 151)  # 600 / 4 + 1: the coarse image is wide enough
    assert search.coarse_bounds(5, 6, 4, 168) == (1, 3)  # never fewer than two disparities


def test_occupied_range_spans_the_quantiles_plus_the_margin():
    disp = torch.full((1, 20, 50), 20.0)
    disp[0, 0, :5] = 30.0   # 5 of 1000 pixels: mismatches that the quantile drops
    disp[0, 1, :] = 22.0    # 50 pixels: part of the scene
    matched = torch.ones_like(disp, dtype=torch.bool)
    assert search.occupied_range(disp, matched, 4, 6.0, 0.005, 0.2, 0, 200) == (74, 96)  # quantiles 80 and 88.2 (interpolated towards 120)
    # clamped to the requested range
    assert search.occupied_range(disp, matched, 4, 6.0, 0.005, 0.2, 78, 90) == (78, 90)
    # nothing seen: search everything
    assert search.occupied_range(disp, torch.zeros_like(matched), 4, 6.0, 0.005, 0.2, 0, 200) is None
    few = torch.zeros_like(matched)
    few[0, :3] = True  # 15 % matched, 20 % needed
    assert search.occupied_range(disp, few, 4, 6.0, 0.005, 0.2, 0, 200) is None


def test_at_narrowed_bound_flags_only_the_moved_bounds():
    index = torch.tensor([[0, 1, 4]])
    assert search.at_narrowed_bound(index, 5, True, True).tolist() == [[True, False, True]]
    assert search.at_narrowed_bound(index, 5, False, True).tolist() == [[False, False, True]]
    assert not search.at_narrowed_bound(index, 5, False, False).any()


def _plate(seed=4):
    # a slanted plate at 36-44 px of a 0-96 search, with a nearer bump on it
    return render(96, 192, [Layer(36.0, 0.03, 0.02), Layer(46.0, 0.0, 0.0, (80, 30, 110, 60))], seed)


def test_coarse_pass_narrows_the_search_to_the_scene():
    left, right, gt, _ = _plate()
    p = TorchSGMParams(preset="seed", search="coarse_to_fine")
    dev = torch.device("cpu")
    with torch.inference_mode():
        lo, hi = coarse_range(bgr_to_tensor(left, dev), bgr_to_tensor(right, dev), 0, 96, p)
    assert lo <= gt.min() and hi > gt.max()
    assert hi - lo <= (gt.max() - gt.min()) + 2 * p.coarse_margin + 6  # not the whole 0-96


def test_coarse_to_fine_gives_the_full_search_result_on_the_scene():
    left, right, gt, nonocc = _plate()
    full, full_ok = compute_disparity(left, right, 0, 96, TorchSGMParams(preset="seed"), device="cpu")
    fast, fast_ok = compute_disparity(left, right, 0, 96, TorchSGMParams(preset="seed", search="coarse_to_fine"), device="cpu")
    inner = nonocc & full_ok
    inner[:, :8] = inner[:, -8:] = inner[:6] = inner[-6:] = False
    diff = np.abs(full - fast)[inner]
    # SGM's penalty is relative to the best disparity searched, so a few pixels move by a tenth
    assert np.percentile(diff, 99) < 0.01 and diff.max() < 0.2
    assert np.abs(fast - gt)[inner & fast_ok].mean() < 0.3


def test_a_surface_outside_the_narrowed_range_is_reported_unmatched():
    # the nearer box is a sixth of the image: a 0.2 quantile drops it from the narrowed range
    left, right, gt, _ = layered_scene(96, 192, seed=5)
    box = gt > 12
    full, full_ok = compute_disparity(left, right, 0, 32, TorchSGMParams(preset="seed"), device="cpu")
    p = TorchSGMParams(preset="seed", search="coarse_to_fine", coarse_quantile=0.2, coarse_margin=2.0)
    disp, matched = compute_disparity(left, right, 0, 32, p, device="cpu")
    assert (np.abs(full - gt)[box] < 1).mean() > 0.75  # the full search sees the box
    assert (np.abs(disp - gt)[box] < 1).mean() == 0.0  # the narrowed one cannot ...
    assert matched[box].mean() < 0.1                    # ... and says so instead of measuring it
    wrong = lambda d, ok: (ok & box & (np.abs(d - gt) > 1)).sum()  # noqa: E731
    assert wrong(disp, matched) <= wrong(full, full_ok)
    assert matched[~box].mean() > 0.8


def test_a_tiny_image_falls_back_to_the_full_search():
    left, right, _, _ = fronto_parallel(24, 40, 5.0, seed=1)
    p = TorchSGMParams(preset="seed", search="coarse_to_fine")
    dev = torch.device("cpu")
    assert coarse_range(bgr_to_tensor(left, dev), bgr_to_tensor(right, dev), 0, 16, p) is None
    a, _ = compute_disparity(left, right, 0, 16, p, device="cpu")
    b, _ = compute_disparity(left, right, 0, 16, TorchSGMParams(preset="seed"), device="cpu")
    assert np.array_equal(a, b)
