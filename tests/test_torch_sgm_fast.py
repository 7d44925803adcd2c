"""The fast torch_sgm stages against the plain stage functions they replace (the references)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plugins.torch_sgm import aggregate, cost, sgm
from plugins.torch_sgm.params import TorchSGMParams
from plugins.torch_sgm.pipeline import bgr_to_tensor, compute_disparity, cost_volume, cost_volume_fast
from plugins.torch_sgm.synthetic import layered_scene
from synthetic_pairs import census_window

pytestmark = pytest.mark.usefixtures("torch_one_thread")
WEIGHTS = dict(w_ad=0.1, w_census=0.6, w_grad=0.3, lam_ad=1.0, lam_census=6.0, lam_grad=0.02)


def pair(h=40, w=56):
    left, right, _, _ = layered_scene(h, w, seed=5)
    return bgr_to_tensor(left, torch.device("cpu")), bgr_to_tensor(right, torch.device("cpu"))


@pytest.mark.parametrize("d_first,count", [(3, 9), (0, 1), (-4, 6), (50, 8)])
def test_shifted_stack_holds_each_shifted_copy(d_first, count):
    features = torch.arange(2 * 3 * 5 * 7, dtype=torch.float32).view(2, 3, 5, 7)
    stack = cost.shifted_stack(features, d_first, count)
    assert stack.shape == (2, 3, count, 5, 7)
    for k in range(count):
        assert torch.equal(stack[:, :, k], cost.shift_right_image(features, d_first - k))
    codes = features.to(torch.int32)
    assert torch.equal(cost.shifted_stack(codes, d_first, count)[:, :, -1], cost.shift_right_image(codes, d_first - count + 1))


@pytest.mark.parametrize("census", ["star24", "window"])
@pytest.mark.parametrize("weights", [WEIGHTS, dict(WEIGHTS, w_ad=0.0), dict(WEIGHTS, w_census=0.0, w_grad=0.0)])
def test_fused_cost_chunk_equals_fused_cost(census, weights):
    left, right = pair()
    offsets = cost.STAR_24 if census == "star24" else census_window(4, 3)
    f = cost.cost_features(left, right, 3, offsets)
    ref = cost.fused_cost(left, right, list(range(2, 13)), znorm_radius=3, features=f, **weights)
    fast = cost.fused_cost_chunk(f, 2, 11, **weights)
    assert fast.shape == ref.shape and torch.allclose(fast, ref, atol=1e-6)


def test_census_factor_table_is_the_robust_term_of_a_half_word():
    table = cost.census_factor_table(6.0)
    codes = torch.tensor([0, 1, 0b101, 2 ** 15 - 1], dtype=torch.int32)
    assert table.shape == (2 ** 15,)
    assert torch.allclose(table[codes.long()], torch.exp(-torch.tensor([0.0, 1.0, 2.0, 15.0]) / 6.0))


@pytest.mark.parametrize("shape", [(8, 8), (17, 30), (40, 56)])
@pytest.mark.parametrize("radius", [1, 3])
def test_box_mean_fast_equals_box_mean(shape, radius):
    x = torch.rand(2, 3, *shape)
    assert torch.allclose(cost.box_mean_fast(x, radius), cost.box_mean(x, radius), atol=1e-5)


def test_box_mean_fast_uses_running_sums_beyond_the_shifted_sums_radius():
    radius = cost.SHIFTED_SUM_MAX_RADIUS + 2
    x = torch.rand(1, 2, 40, 56)
    assert torch.allclose(cost.box_mean_fast(x, radius), cost.box_mean(x, radius), atol=1e-5)


@pytest.mark.parametrize("shape", [(5, 6), (40, 56)])  # (5, 6): too small for running sums, the reference runs
def test_guided_filter_fast_equals_guided_filter(shape):
    guide, src = torch.rand(1, 1, *shape), torch.rand(1, 6, *shape)
    ref = aggregate.guided_filter(guide, src, 3, 1e-3)
    fast = aggregate.guided_filter_fast(aggregate.guide_statistics(guide, 3, 1e-3), src.clone(), 3)
    assert torch.allclose(fast, ref, atol=1e-4)


@pytest.mark.parametrize("paths", [sgm.PATHS_4, sgm.PATHS_8])
def test_sgm_fast_equals_sgm(paths):
    torch.manual_seed(0)
    volume = torch.rand(2, 7, 11, 13)
    p2 = torch.rand(2, 11, 13) + 0.3
    ref = sgm.sgm(volume, 0.1, p2, paths)
    fast = sgm.sgm_fast(volume, 0.1, p2, paths)
    assert torch.allclose(fast, ref, atol=1e-5)
    assert torch.allclose(sgm.sgm_fast(volume, 0.1, 0.5, paths), sgm.sgm(volume, 0.1, 0.5, paths), atol=1e-5)


@pytest.mark.parametrize("paths", [sgm.PATHS_4, sgm.PATHS_8])
def test_sgm_fast_equals_sgm_with_one_p2_map_per_path(paths):
    torch.manual_seed(1)
    volume = torch.rand(2, 7, 11, 13)
    p2 = torch.rand(2, len(paths), 11, 13) + 0.3
    ref = sgm.sgm(volume, 0.1, p2, paths)
    assert torch.allclose(sgm.sgm_fast(volume, 0.1, p2, paths), ref, atol=1e-5)
    # each map must reach its own path: the same maps in another order give another sum
    assert not torch.allclose(sgm.sgm_fast(volume, 0.1, p2.flip(1), paths), ref, atol=1e-3)


def test_sgm_fast_falls_back_for_one_sided_paths():
    volume, p2 = torch.rand(1, 5, 6, 7), torch.rand(1, 6, 7)
    one_way = ((0, 1), (1, 0))
    assert torch.equal(sgm.sgm_fast(volume, 0.1, p2, one_way), sgm.sgm(volume, 0.1, p2, one_way))


def test_fast_cost_volume_equals_reference():
    left, right = pair()
    p = TorchSGMParams(preset="improved")
    assert torch.allclose(cost_volume_fast(left, right, list(range(20)), p), cost_volume(left, right, list(range(20)), p),
                          atol=1e-4)


@pytest.mark.parametrize("preset", ["seed", "improved"])
def test_fast_disparity_equals_reference(preset):
    left, right, _, _ = layered_scene(64, 96, seed=2)
    fast, fast_ok = compute_disparity(left, right, 0, 24, TorchSGMParams(preset=preset), "cpu")
    ref, ref_ok = compute_disparity(left, right, 0, 24, TorchSGMParams(preset=preset, implementation="reference"), "cpu")
    assert (fast_ok == ref_ok).mean() > 0.999
    assert np.abs(fast - ref).max() < 0.02
