"""Each torch_sgm stage as a pure tensor function."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plugins.torch_sgm import aggregate, cost, refine, select, sgm
from plugins.torch_sgm.params import TorchSGMParams
from plugins.torch_sgm.pipeline import bgr_to_tensor, cost_volume, cost_volume_fast, edge_strength
from plugins.torch_sgm.synthetic import fronto_parallel
from synthetic_pairs import census_window


pytestmark = pytest.mark.usefixtures("torch_one_thread")


def shifted_pair(d=5, h=40, w=64):
    left, right, _, _ = fronto_parallel(h, w, float(d), seed=3)
    return bgr_to_tensor(left, torch.device("cpu")), bgr_to_tensor(right, torch.device("cpu"))


def interior_argmin(volume, d_max):
    return volume[0, :, 4:-4, d_max + 4:-4].argmin(0)


def test_census_cost_is_minimal_at_the_true_disparity():
    left, right = shifted_pair(5)
    f = cost.cost_features(left, right, 3)
    volume = cost.census_cost(f["cl"], f["cr"], range(12))
    best = interior_argmin(volume, 12)
    assert (best == 5).float().mean() > 0.98
    assert volume.shape == (1, 12, 40, 64)


def test_census_uses_24_bits_and_counts_hamming_distance():
    grey = torch.rand(1, 1, 20, 20)
    bits = cost.census_transform(grey)
    assert bits.shape == (1, 24, 20, 20)
    code = cost.pack_bits(bits)
    assert code.shape == (1, 1, 20, 20)
    assert torch.equal(cost.popcount(code).sum(1), bits.sum(1).int())
    window = cost.census_transform(grey, census_window(4, 3))
    assert window.shape[1] == 62 and cost.pack_bits(window).shape[1] == 3
    assert torch.equal(cost.popcount(cost.pack_bits(window)).sum(1), window.sum(1).int())
    words = cost.pack_bits(window)
    for k in range(window.shape[1]):  # bit k of the string is bit k % 30 of word k // 30
        assert torch.equal(((words[:, k // 30] >> (k % 30)) & 1).bool(), window[:, k])
    assert cost.popcount(torch.tensor([0, 1, 0xFFFFFF, 0b1011, 2**30 - 1])).tolist() == [0, 1, 24, 3, 30]


@pytest.mark.parametrize("which", ["ad", "grad"])
def test_ad_and_gradient_costs_are_minimal_at_the_true_disparity(which):
    left, right = shifted_pair(7)
    f = cost.cost_features(left, right, 3)
    volume = (cost.ad_cost(f["zl"], f["zr"], range(12)) if which == "ad"
              else cost.gradient_cost(f["gl"], f["gr"], range(12)))
    assert (interior_argmin(volume, 12) == 7).float().mean() > 0.9


def test_zero_normalisation_ignores_gain_and_offset():
    image = torch.rand(1, 3, 30, 30)
    a = cost.zero_normalise(image, 3)
    b = cost.zero_normalise(image * 0.5 + 0.2, 3, eps=1e-3 * 0.5)
    assert torch.allclose(a, b, atol=1e-4)


def test_robust_transform_maps_costs_into_unit_interval():
    c = torch.tensor([0.0, 1.0, 6.0, 1e6])
    r = cost.robust(c, 6.0)
    assert r[0] == 0 and torch.all((r >= 0) & (r <= 1)) and torch.all(r[1:3] > r[:2])
    assert torch.isclose(r[2], torch.tensor(1 - np.exp(-1.0), dtype=torch.float32))


def test_box_mean_matches_average_pooling_at_the_borders():
    x = torch.rand(1, 2, 17, 23)
    expected = torch.nn.functional.avg_pool2d(x, 7, 1, 3, count_include_pad=False)
    assert torch.allclose(cost.box_mean(x, 3), expected, atol=1e-5)


def test_guided_filter_keeps_constants_and_guide_edges():
    guide = torch.zeros(1, 1, 20, 20)
    guide[..., 10:] = 1.0
    src = torch.stack([torch.full((20, 20), 0.3), guide[0, 0] * 2.0])[None]
    out = aggregate.guided_filter(guide, src, 3, 1e-3)
    assert torch.allclose(out[0, 0], torch.full((20, 20), 0.3), atol=1e-5)
    # A step aligned with the guide's edge survives instead of being blurred into a ramp.
    assert out[0, 1, :, 8].max() < 0.05 and out[0, 1, :, 11].min() > 1.95


def test_texture_weight_is_one_on_flat_areas_and_falls_with_contrast():
    flat = torch.full((2, 1, 12, 16), 0.4)
    assert torch.allclose(aggregate.texture_weight(flat, 2, 0.02), torch.ones(2, 1, 12, 16))
    checker = (torch.arange(16)[None, :] + torch.arange(12)[:, None]) % 2
    images = [(0.5 + contrast * (checker - 0.5))[None, None].float() for contrast in (0.01, 0.05, 0.5)]
    weights = [aggregate.texture_weight(image, 2, 0.02)[0, 0, 2:-2, 2:-2] for image in images]
    assert weights[0].min() > weights[1].max() and weights[1].min() > weights[2].max()
    assert weights[2].max() < 1e-3  # strong texture: the narrow aggregation alone


@pytest.mark.parametrize("implementation", ["reference", "fast"])
def test_texture_blend_aggregates_narrowly_on_texture_and_widely_on_flat_areas(implementation):
    volume = cost_volume if implementation == "reference" else cost_volume_fast
    gen = torch.Generator().manual_seed(0)
    left = torch.rand(1, 3, 32, 48, generator=gen)
    left[..., 24:] = 0.5  # the right third of the left image is flat
    right = torch.rand(1, 3, 32, 48, generator=gen)
    disparities = list(range(6))
    # a sharp texture scale, so that the random texture counts as fully textured
    blended = volume(left, right, disparities, TorchSGMParams(preset="seed", agg_radius=3, agg_detail_radius=0, agg_texture=0.005))
    narrow = volume(left, right, disparities, TorchSGMParams(preset="seed", agg_radius=0))
    wide = volume(left, right, disparities, TorchSGMParams(preset="seed", agg_radius=3))
    assert not torch.allclose(narrow[..., 3:21], wide[..., 3:21], atol=1e-2)  # the check below can fail
    assert torch.allclose(blended[..., 3:21], narrow[..., 3:21], atol=1e-4)
    assert torch.allclose(blended[..., 27:], wide[..., 27:], atol=1e-4)
    # in between, the mix stays within the two aggregations
    low, high = torch.minimum(narrow, wide) - 1e-5, torch.maximum(narrow, wide) + 1e-5
    assert ((blended >= low) & (blended <= high)).all()


def test_sgm_without_penalties_equals_raw_wta():
    volume = torch.rand(1, 9, 12, 15)
    out = sgm.sgm(volume, 0.0, 0.0, sgm.PATHS_8)
    assert torch.allclose(out, 8 * volume, atol=1e-5)
    assert torch.equal(out.argmin(1), volume.argmin(1))


def _reference_path(cost_np, p1, p2, dy, dx):
    """Straightforward per-pixel recurrence, the definition the vectorised walk must match."""
    d, h, w = cost_np.shape
    out = np.zeros_like(cost_np)
    ys = range(h) if dy >= 0 else range(h - 1, -1, -1)
    xs = range(w) if dx >= 0 else range(w - 1, -1, -1)
    order = [(y, x) for x in xs for y in ys] if dx else [(y, x) for y in ys for x in xs]
    for y, x in order:
        py, px = y - dy, x - dx
        if not (0 <= py < h and 0 <= px < w):
            out[:, y, x] = cost_np[:, y, x]
            continue
        prev = out[:, py, px]
        m = prev.min()
        up = np.concatenate([[np.inf], prev[:-1]]) + p1
        down = np.concatenate([prev[1:], [np.inf]]) + p1
        out[:, y, x] = cost_np[:, y, x] + np.minimum.reduce([prev, up, down, np.full(d, m + p2[y, x])]) - m
    return out


@pytest.mark.parametrize("direction", sgm.PATHS_8)
def test_each_path_matches_the_per_pixel_recurrence(direction):
    rng = np.random.default_rng(1)
    volume = rng.random((6, 7, 9)).astype(np.float32)
    p2 = (0.3 + rng.random((7, 9))).astype(np.float32)
    got = sgm.sgm(torch.from_numpy(volume)[None], 0.1, torch.from_numpy(p2)[None], (direction,))[0].numpy()
    assert np.allclose(got, _reference_path(volume, 0.1, p2, *direction), atol=1e-5)


def test_per_path_p2_maps_each_reach_their_own_path():
    rng = np.random.default_rng(2)
    volume = rng.random((6, 7, 9)).astype(np.float32)
    p2 = (0.3 + rng.random((8, 7, 9))).astype(np.float32)
    got = sgm.sgm(torch.from_numpy(volume)[None], 0.1, torch.from_numpy(p2)[None], sgm.PATHS_8)[0].numpy()
    want = sum(_reference_path(volume, 0.1, p2[k], *path) for k, path in enumerate(sgm.PATHS_8))
    assert np.allclose(got, want, atol=1e-4)
    with pytest.raises(ValueError, match="4 P2 maps for 8 paths"):
        sgm.sgm(torch.from_numpy(volume)[None], 0.1, torch.from_numpy(p2[:4])[None], sgm.PATHS_8)


def test_sgm_overrules_an_isolated_wrong_minimum():
    volume = torch.ones(1, 8, 9, 9)
    volume[:, 3] = 0.0
    volume[0, 3, 4, 4] = 0.2
    volume[0, 6, 4, 4] = 0.0  # one pixel prefers d = 6, by less than the jump penalty
    out = sgm.sgm(volume, 0.05, 0.5)
    assert out.argmin(1)[0, 4, 4] == 3


def test_adaptive_p2_drops_at_edges_but_not_below_p1():
    edge = torch.tensor([[[0.0, 0.05, 10.0]]])
    p2 = sgm.adaptive_p2(edge, 0.65, 20.0, 0.04)
    assert torch.allclose(p2, torch.tensor([[[0.65, 0.325, 0.04]]]))


def test_path_p2_drops_only_for_paths_that_cross_an_edge():
    grey = torch.zeros(1, 5, 8)
    grey[..., 4:] = 0.5  # a vertical edge between columns 3 and 4
    p2 = sgm.path_p2(grey, sgm.PATHS_8, 0.65, 20.0, 0.04)  # (1, 8, 5, 8)
    across = sgm.PATHS_8.index((0, 1))  # left to right: column 4's predecessor is column 3
    along = sgm.PATHS_8.index((1, 0))
    diagonal = sgm.PATHS_8.index((1, 1))
    assert torch.allclose(p2[0, across, :, 4], torch.full((5,), 0.65 / 11))
    assert torch.allclose(p2[0, diagonal, 1:, 4], torch.full((4,), 0.65 / 11))
    assert torch.allclose(p2[0, along], torch.full((5, 8), 0.65))  # running along the edge: no drop
    assert torch.allclose(p2[0, across, :, 3], torch.full((5,), 0.65))  # the step lies behind column 4
    opposite = sgm.PATHS_8.index((0, -1))  # right to left: column 3's predecessor is column 4
    assert torch.allclose(p2[0, opposite, :, 3], torch.full((5,), 0.65 / 11))
    # the magnitude version lowers P2 for every path through the edge, the one along it as well
    magnitude = edge_strength(grey.unsqueeze(1).expand(-1, 3, -1, -1))
    assert torch.all(sgm.adaptive_p2(magnitude, 0.65, 20.0, 0.04)[0, :, 3:5] < 0.65)
    assert torch.allclose(sgm.path_p2(grey * 100, sgm.PATHS_4, 0.65, 20.0, 0.04).amin(), torch.tensor(0.04))


def test_parabola_finds_the_subpixel_minimum():
    d = torch.arange(10, dtype=torch.float32).view(1, 10, 1, 1)
    volume = (d - 4.3) ** 2
    index = select.winner_takes_all(volume)
    assert index.item() == 4
    assert abs(select.parabolic_subpixel(volume, index).item() - 4.3) < 1e-4


def test_parabola_leaves_range_ends_integer():
    volume = torch.arange(5, dtype=torch.float32).view(1, 5, 1, 1)
    assert select.parabolic_subpixel(volume, select.winner_takes_all(volume)).item() == 0.0


def test_uniqueness_rejects_a_second_minimum_far_away_but_not_the_winners_own_slope():
    d = torch.arange(12, dtype=torch.float32)
    single = (d - 4.0).abs() + 1.0                           # one V-shaped minimum at 4
    double = torch.minimum((d - 4.0).abs(), (d - 9.0).abs() + 0.05) + 1.0  # a rival at 9, 5 % worse
    volume = torch.stack([single, double], -1).view(1, 12, 1, 2)
    index = select.winner_takes_all(volume)
    assert index.flatten().tolist() == [4, 4]
    unique = select.unique_minimum(volume.clone(), index, 0.1)
    # the single minimum: its ±1 neighbours (cost 2.0) are ignored, the next (3.0) beats 1.1 * 1.0
    assert unique.flatten().tolist() == [True, False]
    assert select.unique_minimum(volume.clone(), index, 0.01).flatten().tolist() == [True, True]
    assert select.unique_minimum(volume.clone(), index, 2.5).flatten().tolist() == [False, False]


def test_right_view_wta_reads_the_volume_along_diagonals():
    rng = torch.Generator().manual_seed(0)
    volume = torch.rand(1, 5, 3, 8, generator=rng)
    disparities = [2, 3, 4, 5, 6]
    got = select.right_view_wta(volume, disparities)
    for x in range(8):
        costs = [volume[0, k, 1, x + d].item() if x + d < 8 else np.inf for k, d in enumerate(disparities)]
        expected = np.nan if np.isinf(min(costs)) else disparities[int(np.argmin(costs))]
        assert np.isnan(expected) and torch.isnan(got[0, 1, x]) or got[0, 1, x].item() == expected


def test_local_winners_keep_the_raw_minimum_where_both_views_agree():
    # a pair shifted by 3 px: the cost is lowest at d = 3 everywhere but one pixel, whose own minimum
    # at d = 5 the right view does not confirm: right x = 4 sees left x = 7 at d = 3 at a lower cost
    disparities = [1, 2, 3, 4, 5, 6]
    volume = torch.ones(1, 6, 2, 12)
    volume[:, 2] = 0.1
    volume[0, :, 0, 9] = torch.tensor([1.0, 1.0, 0.5, 1.0, 0.15, 1.0])
    got = select.local_winners(volume, disparities, lr_tolerance=1.0)
    assert torch.isnan(got[0, :, :3]).all()  # x - 3 leaves the right image
    assert (got[0, 1, 3:] == 3).all() and (got[0, 0, 3:9] == 3).all() and (got[0, 0, 10:] == 3).all()
    assert torch.isnan(got[0, 0, 9])


def test_checked_winners_refine_the_winner_and_leave_the_volume_for_the_uniqueness_test():
    # every pixel's cost is a parabola with its minimum at d = 3.25, except one pixel whose minimum at
    # d = 5 the right view does not confirm (as in the test above)
    disparities = [1, 2, 3, 4, 5, 6]
    d = torch.tensor(disparities, dtype=torch.float32).view(1, 6, 1, 1)
    volume = ((d - 3.25) ** 2).expand(1, 6, 2, 12).contiguous()
    volume[0, :, 0, 9] = torch.tensor([1.0, 1.0, 0.5, 1.0, 0.15, 1.0])
    before = volume.clone()
    disp, index, right_disp, consistent = select.checked_winners(volume, disparities, 1.0)
    assert torch.equal(volume, before)
    assert index[0, 1, 5] == 2 and index[0, 0, 9] == 4
    assert torch.allclose(disp[0, 1], torch.full((12,), 3.25))  # a parabola's vertex is found exactly
    assert not consistent[0, 0, 9] and consistent[0, 1, 3:].all() and not consistent[0, :, :3].any()
    assert torch.equal(consistent, refine.left_right_check(disp, right_disp, 1.0))


def test_left_right_check_rejects_inconsistent_pixels():
    left = torch.full((1, 1, 10), 2.0)
    right = torch.full((1, 1, 10), 2.0)
    right[0, 0, 5] = 6.0  # seen by left x = 7
    ok = refine.left_right_check(left, right, 1.0)
    assert not ok[0, 0, :2].any()  # x - d leaves the image
    assert not ok[0, 0, 7] and ok[0, 0, 2:7].all() and ok[0, 0, 8:].all()


def test_background_filling_takes_the_farther_side():
    nan = float("nan")
    disp = torch.tensor([[[nan, 9.0, nan, nan, 3.0, nan]]])
    filled = refine.fill_horizontal(disp)
    assert filled.tolist() == [[[9.0, 9.0, 3.0, 3.0, 3.0, 3.0]]]


def test_filling_with_slopes_carries_each_side_along_its_surface():
    nan = float("nan")
    # a wall slanting by 0.5 per pixel with a hole at the row's start and one in the middle; the
    # right side of the middle hole is a nearer, fronto-parallel box (slope 0)
    disp = torch.tensor([[[nan, nan, 11.0, 11.5, 12.0, nan, nan, 30.0, 30.0]]])
    slope = torch.tensor([[[nan, nan, 0.5, 0.5, 0.5, nan, nan, 0.0, 0.0]]])
    filled = refine.fill_horizontal(disp, slope)
    assert filled.tolist() == [[[10.0, 10.5, 11.0, 11.5, 12.0, 12.5, 13.0, 30.0, 30.0]]]
    # without slopes (or where a side has none) the side's value is copied, as before
    assert refine.fill_horizontal(disp)[0, 0, :2].tolist() == [11.0, 11.0]
    no_slope = torch.full_like(slope, nan)
    assert torch.equal(refine.fill_horizontal(disp, no_slope), refine.fill_horizontal(disp))


def test_out_of_view_drops_a_border_match_that_its_own_surface_could_not_see():
    # one region, a wall at disparity 20 from column 20 on; columns 0-3 matched 0 and 1, which
    # the wall (d = 20 > x) cannot have: their match would lie left of the right image
    w = 40
    disp = torch.full((1, 2, w), 20.0)
    disp[:, :, :4] = torch.tensor([0.0, 0.0, 1.0, 0.0])
    matched = torch.zeros(1, 2, w, dtype=torch.bool)
    matched[:, :, :4] = True
    matched[:, :, 20:] = True
    labels = torch.ones(1, 2, w, dtype=torch.int64)
    # row 1: an edge at column 10 separates the border pixels from the wall (a nearer object's
    # boundary), so a small disparity there is plausible and is kept
    labels[0, 1, 10:] = 2
    suspect = refine.out_of_view(disp, matched, labels)
    assert suspect[0, 0].nonzero()[:, 0].tolist() == [0, 1, 2, 3]
    assert not suspect[0, 1].any()
    # a slanted wall d = 15 + 0.2 x comes into view at x = 18.75: its matches from there on, the
    # first ones included, are kept
    xs = torch.arange(w, dtype=torch.float32)
    wall = (15 + 0.2 * xs).view(1, 1, w)
    seen = (xs >= 19).view(1, 1, w)
    assert not refine.out_of_view(wall, seen, labels[:, :1]).any()


def test_median_fill_leaves_no_hole_and_removes_streaks():
    disp = torch.full((1, 9, 9), 4.0)
    disp[0, 4, 2:7] = 9.0  # a streak from row-wise filling
    holes = torch.zeros(1, 9, 9, dtype=torch.bool)
    holes[0, 4, 2:7] = True
    disp[0, 0, 0] = float("nan")
    out = refine.median_fill(disp, holes, 1)
    assert torch.isfinite(out).all()
    assert torch.allclose(out[0, 4, 2:7], torch.full((5,), 4.0))


def test_winner_takes_all_picks_the_first_of_equal_minima():
    volume = torch.tensor([3.0, 1.0, 2.0, 1.0, 1.0]).view(1, 5, 1, 1).repeat(1, 1, 2, 3)
    volume[0, 1, 0, 0] = 5.0  # here the first minimum is at index 3
    assert select.winner_takes_all(volume).tolist() == [[[3, 1, 1], [1, 1, 1]]]


def test_median_at_equals_the_median_filter_where_asked():
    torch.manual_seed(0)
    disp = torch.rand(2, 17, 23) * 10
    disp[disp < 1.5] = float("nan")
    where = torch.rand(2, 17, 23) < 0.3
    out = refine.median_at(disp, where, 2)
    full = refine.median_filter(disp, 2)
    assert torch.equal(out[where].nan_to_num(-1), full[where].nan_to_num(-1))
    assert torch.equal(out[~where].nan_to_num(-1), disp[~where].nan_to_num(-1))
    assert refine.median_at(disp, torch.zeros_like(where), 2) is disp


def test_weighted_median_moves_a_fattened_disparity_edge_onto_the_colour_edge():
    # the foreground (columns 0-19, red) carries its disparity 2 px into the grey background
    image = torch.full((1, 3, 24, 40), 0.5)
    image[:, :, :, :20] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    disp = torch.full((1, 24, 40), 10.0)
    disp[:, :, :22] = 30.0
    out = refine.weighted_median(disp, image, 4, 0.1, 7.0)
    assert torch.equal(out[:, :, :20], torch.full((1, 24, 20), 30.0))
    assert torch.equal(out[:, :, 20:], torch.full((1, 24, 20), 10.0))
    # with colour ignored the plain median keeps the fattened band
    assert (refine.weighted_median(disp, image, 4, 1e3, 1e3)[:, :, 20:22] == 30.0).all()


def test_weighted_median_with_flat_weights_is_the_plain_median_and_radius_zero_is_a_no_op():
    gen = torch.Generator().manual_seed(3)
    disp = torch.rand(2, 30, 37, generator=gen) * 50
    image = torch.rand(2, 3, 30, 37, generator=gen)
    # 100 pixels per step, so that the chunk loop is exercised as well
    refine._WEIGHTED_MEDIAN_PIXELS, saved = 100, refine._WEIGHTED_MEDIAN_PIXELS
    try:
        flat = refine.weighted_median(disp, image, 2, 1e6, 1e6)
    finally:
        refine._WEIGHTED_MEDIAN_PIXELS = saved
    assert torch.equal(flat, refine.median_filter(disp, 2))
    assert refine.weighted_median(disp, image, 0, 0.1, 7.0) is disp


def test_weighted_median_with_a_jump_threshold_filters_only_windows_that_span_an_edge():
    gen = torch.Generator().manual_seed(5)
    disp = 20 + 0.3 * torch.rand(1, 32, 40, generator=gen)  # smooth: every window spans < 0.3 px
    disp[:, 10:20, 15:25] += 10  # except around this block
    image = torch.full((1, 3, 32, 40), 0.5)  # one colour: every neighbour counts, so filtering changes a pixel
    every = refine.weighted_median(disp, image, 3, 0.1, 7.0)
    edges = refine.weighted_median(disp, image, 3, 0.1, 7.0, jump=1.0)
    span = torch.zeros_like(disp, dtype=torch.bool)
    span[:, 7:23, 12:28] = True  # pixels whose 7x7 window reaches the block
    span[:, 13:17, 18:22] = False  # the block's middle, whose window stays inside it
    assert torch.equal(edges[span], every[span])
    assert torch.equal(edges[~span], disp[~span])
    assert not torch.equal(every[~span], disp[~span])


def _slanted_plane(h: int, w: int) -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    return (20 + 0.3 * x + 0.15 * y)[None]


def test_local_plane_fit_puts_a_pixel_locked_staircase_back_on_its_slope():
    plane = _slanted_plane(40, 60)
    locked = plane.round()  # winner-takes-all's integer steps, up to 0.5 px off
    image = torch.full((1, 3, 40, 60), 0.5)
    out = refine.local_plane_fit(locked, image, 3, 0.1, 5.0, 1.0)
    assert (locked - plane).abs().mean() > 0.2
    assert (out - plane).abs().mean() < 0.05
    assert (out - plane).abs().max() < 0.2  # the image border included: outside pixels take no part


def test_local_plane_fit_keeps_a_differently_coloured_surface_out_of_the_fit():
    plane = _slanted_plane(40, 60)
    image = torch.full((1, 3, 40, 60), 0.5)
    image[:, :, :, 30:] = torch.tensor([0.9, 0.1, 0.1])[:, None, None]
    disp = plane.clone()
    disp[:, :, 30:] += 0.8  # a nearer surface, close enough to pass the disparity tolerance
    coloured = refine.local_plane_fit(disp, image, 3, 0.1, 5.0, 1.0)
    blind = refine.local_plane_fit(disp, image, 3, 1e3, 5.0, 1.0)
    assert (coloured - disp).abs().max() < 1e-3  # each side is an exact plane of its own colour
    assert (blind - disp)[:, :, 29:31].abs().mean() > 0.1  # without colour the two surfaces blur together


def test_local_plane_fit_leaves_exact_planes_and_holes_alone():
    gen = torch.Generator().manual_seed(7)
    disp = _slanted_plane(30, 37).repeat(2, 1, 1)
    disp[1] = 50 - 0.2 * disp[1]
    disp[0, 12:15, 20:24] = float("nan")
    image = torch.rand(2, 3, 30, 37, generator=gen)
    out = refine.local_plane_fit(disp, image, 4, 0.1, 5.0, 1.0)
    finite = torch.isfinite(disp)
    assert torch.equal(torch.isfinite(out), finite)
    assert torch.allclose(out[finite], disp[finite], atol=1e-3)
    assert refine.local_plane_fit(disp, image, 0, 0.1, 5.0, 1.0) is disp


def _square_scene(fattening: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A background at 10 px with a square at 20 px (left columns 20-39, rows 10-29): the right view's
    exact map, and a left map whose square is fattened by ``fattening`` px to its right."""
    right = torch.full((1, 40, 64), 10.0)
    right[0, 10:30, 0:20] = 20.0
    left = torch.full((1, 40, 64), 10.0)
    left[0, 10:30, 20:40 + fattening] = 20.0
    return left, right


def test_view_mismatch_measures_the_disagreement_and_is_inf_out_of_view():
    left, right = _square_scene(3)
    miss = refine.view_mismatch(left, right)
    assert torch.isinf(miss[0, 0, :10]).all()  # x - 10 < 0
    assert (miss[0, 10:30, 20:40] == 0).all() and (miss[0, 10:30, 40:43] == 10).all()
    assert torch.isinf(refine.view_mismatch(torch.full((1, 1, 4), float("nan")), right[:, :1, :4])).all()


def test_two_view_choice_gives_a_fattened_edge_back_to_the_background():
    left, right = _square_scene(3)
    chosen = refine.two_view_choice(left, right, reach=6, tolerance=1.0, iterations=1)
    assert (chosen[0, 10:30, 40:43] == 10).all()
    assert torch.equal(chosen[0, 10:30, 20:40], left[0, 10:30, 20:40])  # what the right view confirms stays
    truth, _ = _square_scene(0)
    assert torch.equal(chosen[:, :, 10:], truth[:, :, 10:])


def test_two_view_choice_keeps_a_value_no_neighbour_can_replace_and_iterates_to_reach_further():
    left, right = _square_scene(10)  # columns 40-49 wrong, the nearest right background 10 px away
    once = refine.two_view_choice(left, right, reach=4, tolerance=1.0, iterations=1)
    # rows more than 4 px inside the square have no confirmed value within reach of columns 40-45
    assert (once[0, 10:30, 46:50] == 10).all() and (once[0, 14:26, 40:46] == 20).all()
    more = refine.two_view_choice(left, right, reach=4, tolerance=1.0, iterations=3)
    assert (more[0, 10:30, 40:50] == 10).all()
    # a right map that confirms nothing changes nothing
    nothing = refine.two_view_choice(left, torch.full_like(right, 50.0), reach=4, tolerance=1.0)
    assert torch.equal(nothing, left)


def test_two_view_choice_takes_the_confirmed_value_closest_to_the_contradicted_one():
    left = torch.full((1, 1, 40), 30.0)
    left[0, 0, 28], left[0, 0, 30], left[0, 0, 32] = 12.2, 14.0, 10.0
    right = torch.full((1, 1, 40), 50.0)
    right[0, 0, 16] = 5.0    # seen from column 30 at 14: contradicted
    right[0, 0, 18] = 11.5   # at 12.2 (the left neighbour's value): confirmed, 0.7 px off
    right[0, 0, 20] = 10.0   # at 10 (the right neighbour's value): confirmed exactly
    chosen = refine.two_view_choice(left, right, reach=2, tolerance=1.0, iterations=1)
    # the least change the right view accepts, not the value it confirms best
    assert chosen[0, 0, 30] == pytest.approx(12.2)
    right[0, 0, 18] = 50.0  # now only 10 is confirmed
    assert refine.two_view_choice(left, right, reach=2, tolerance=1.0, iterations=1)[0, 0, 30] == 10.0


def test_right_view_at_interpolates_the_right_map_between_columns():
    right = torch.arange(10.0).view(1, 1, 10).repeat(1, 2, 1) * 0.5 + 3.0  # a slanted right map
    left = torch.tensor([[[2.5, 2.5, 2.5, 2.5, 2.5, 2.5, 2.5, 2.5, 2.5, 2.5],
                          [0.0, 1.0, float("nan"), 20.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]]])
    seen = refine.right_view_at(left, right)
    # column x - 2.5: halfway between two right pixels, so halfway between their values
    assert torch.allclose(seen[0, 0, 3:], 3.0 + 0.5 * (torch.arange(3.0, 10.0) - 2.5))
    assert torch.isnan(seen[0, 0, :3]).all()  # x - 2.5 < 0
    assert torch.allclose(seen[0, 1, [0, 1, 4]], torch.tensor([3.0, 3.0, 5.0]))
    assert torch.isnan(seen[0, 1, 2:4]).all()  # a NaN disparity, and a column left of the image
    assert seen[0, 1, 9] == 7.5  # the last column itself, with no neighbour to its right


def test_two_view_average_halves_a_disagreement_within_tolerance_and_keeps_larger_ones():
    left, right = _square_scene(0)
    left[0, 0:5] += 0.6   # the two maps 0.6 px apart: within the tolerance
    left[0, 35:40] += 3.0  # 3 px apart: the right map does not see the same point
    averaged = refine.two_view_average(left, right, tolerance=1.0)
    assert torch.allclose(averaged[0, 0:5, 20:], torch.full((5, 44), 10.3))
    assert torch.equal(averaged[0, 35:40], left[0, 35:40])
    assert torch.equal(averaged[0, 10:30, 20:40], left[0, 10:30, 20:40])  # agreeing exactly: unchanged
    assert torch.equal(averaged[0, :, :10], left[0, :, :10])  # x - d out of the image: the left value
