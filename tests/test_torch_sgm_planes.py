"""Slanted-plane filling (plugins/torch_sgm/planes.py), one test per stage function."""
from __future__ import annotations

import pytest
import torch

from plugins.torch_sgm import planes

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def test_edge_regions_split_at_a_colour_step_and_stay_unique_across_the_batch():
    h, w = 40, 60
    ramp = torch.linspace(0.2, 0.3, w).expand(h, w)  # a gentle shading is not an edge
    first = torch.where(torch.arange(w) < 30, ramp, torch.full((h, w), 0.8))
    image = torch.stack([first.expand(3, h, w), torch.full((3, h, w), 0.5)])
    labels = planes.edge_regions(planes.edge_magnitude(image, sigma=1.0), threshold=0.01)
    assert labels.shape == (2, h, w)
    left_side, right_side = labels[0, :, :25], labels[0, :, 35:]
    assert left_side.unique().numel() == 1 and right_side.unique().numel() == 1
    assert left_side[0, 0] != right_side[0, 0] and left_side[0, 0] > 0 and right_side[0, 0] > 0
    assert (labels[0, :, 29:31] == 0).all()  # the step itself is an edge
    assert labels[1].unique().tolist() == [3]  # the flat image is one region, numbered after the first's two


def slanted(h=50, w=80):
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    return 0.3 * x + 0.1 * y + 20.0


def test_region_planes_recover_a_slanted_plane_through_mismatches_and_holes():
    truth = slanted()
    gen = torch.Generator().manual_seed(1)
    matched = torch.rand(truth.shape, generator=gen) < 0.6
    wrong = matched & (torch.rand(truth.shape, generator=gen) < 0.25)  # a quarter of the matches are off
    disp = torch.where(wrong, truth + 5 + 15 * torch.rand(truth.shape, generator=gen), truth)
    labels = torch.ones(1, *truth.shape, dtype=torch.int64)
    plane, supported = planes.region_planes(disp[None], matched[None], labels, min_pixels=100, inlier_share=0.6)
    assert supported.all()
    assert (plane[0] - truth).abs().max() < 0.01
    # plain least squares would not get there: the mismatches pull it by whole pixels
    plain = disp[matched].mean() - truth[matched].mean()
    assert plain > 1.0


def test_regions_without_a_plane_too_few_matches_or_on_edges_are_not_supported():
    h, w = 50, 80
    truth = slanted(h, w)
    gen = torch.Generator().manual_seed(2)
    labels = torch.zeros(1, h, w, dtype=torch.int64)
    labels[0, :, :30] = 1   # random disparities: no plane explains them
    labels[0, :, 30:60] = 2  # a plane, but only a few matched pixels
    # columns 60.. are edge pixels (label 0), fully matched on the plane
    disp = torch.where(torch.arange(w) < 30, 50 * torch.rand(h, w, generator=gen), truth)
    matched = torch.ones(h, w, dtype=torch.bool)
    matched[:, 30:60] = False
    matched[:2, 30:60] = True  # 60 matched pixels
    plane, supported = planes.region_planes(disp[None], matched[None], labels, min_pixels=100, inlier_share=0.6)
    assert not supported.any()
    _, lenient = planes.region_planes(disp[None], matched[None], labels, min_pixels=50, inlier_share=0.6)
    assert not lenient[0, :, :30].any() and lenient[0, :, 30:60].all() and not lenient[0, :, 60:].any()
    # a region with no pixel that wants a plane is not fitted at all
    wanted = torch.zeros(1, h, w, dtype=torch.bool)
    wanted[0, 5, 5] = True
    plane, skipped = planes.region_planes(disp[None], matched[None], labels, min_pixels=50, inlier_share=0.6,
                                          wanted=wanted)
    assert not skipped.any() and torch.isnan(plane[0, :, 30:]).all() and torch.isfinite(plane[0, :, :30]).all()


def test_fill_from_planes_takes_the_finest_supported_region_and_leaves_the_rest():
    h, w = 40, 60
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    # left half: a faint step (0.3 -> 0.31) between two slanted surfaces; right half: a strong edge
    # closes off a third surface that has no matched pixel at all
    grey = torch.where(x < 15, 0.30, 0.31)
    grey = torch.where(x >= 30, torch.where(x < 45, 0.9, 0.1), grey)
    image = grey.expand(1, 3, h, w).contiguous()
    truth = torch.where(x < 15, 0.2 * x + 10, -0.1 * x + 20)
    matched = (x % 3 != 0) & (x < 45)
    matched[:, 28:32] = False
    filled = torch.full((1, h, w), -1.0)
    out = planes.fill_from_planes(filled, truth[None], matched[None], image, [0.0025, 0.005, 0.01, 0.02],
                                  sigma=1.0, min_pixels=50, inlier_share=0.6)[0]
    holes = ~matched
    inner = holes & ((x < 12) | ((x > 18) & (x < 26)))  # away from the blurred edges
    # the faint step splits the two surfaces at the finest threshold, so each keeps its own plane
    assert (out[inner] - truth[inner]).abs().max() < 1e-3
    assert (out[matched] == -1).all()  # matched pixels are not touched
    assert (out[:, 46:] == -1).all()  # a region with no matched pixel has no plane


def test_planes_and_slopes_give_each_supported_region_its_row_slope():
    h, w = 40, 60
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    grey = torch.where(x < 30, 0.3, 0.8)
    image = grey.expand(1, 3, h, w).contiguous()
    truth = torch.where(x < 30, 0.25 * x + 0.1 * y + 10, -0.5 * x + 40)
    matched = (x % 3 != 0) & (x < 50)
    filled, slope = planes.planes_and_slopes(torch.full((1, h, w), -1.0), truth[None], matched[None],
                                             planes.edge_magnitude(image, 1.0), [0.01], min_pixels=50,
                                             inlier_share=0.6)
    assert torch.equal(filled, planes.fill_from_planes(torch.full((1, h, w), -1.0), truth[None], matched[None],
                                                       image, [0.01], sigma=1.0, min_pixels=50, inlier_share=0.6))
    left, right = x < 26, (x > 34) & (x < 58)  # inside each region, away from the blurred edge
    # matched pixels get their region's slope too: a filler reads it from the hole's neighbours
    assert (slope[0][left] - 0.25).abs().max() < 1e-3
    assert (slope[0][right] + 0.5).abs().max() < 1e-3


def test_row_slope_steps_within_a_region_only():
    plane = torch.tensor([[[1.0, 2.0, 3.0, 10.0, 10.5, 7.0]]])
    labels = torch.tensor([[[1, 1, 1, 2, 2, 3]]])
    slope = planes.row_slope(plane, labels)[0, 0]
    assert slope[:5].tolist() == [1.0, 1.0, 1.0, 0.5, 0.5]  # a region's last pixel takes the step before it
    assert torch.isnan(slope[5])  # alone in its region on this row


def test_ransac_start_finds_the_plane_when_most_matches_are_wrong():
    truth = slanted()
    gen = torch.Generator().manual_seed(3)
    wrong = torch.rand(truth.shape, generator=gen) < 0.6  # most "matches" sit 2-12 px off the surface
    disp = torch.where(wrong, truth + 2 + 10 * torch.rand(truth.shape, generator=gen), truth)
    matched = torch.ones(1, *truth.shape, dtype=torch.bool)
    labels = torch.ones(1, *truth.shape, dtype=torch.int64)
    plane, supported = planes.region_planes(disp[None], matched, labels, min_pixels=100, inlier_share=0.3, samples=32)
    assert supported.all() and (plane[0] - truth).abs().max() < 0.01
    again, _ = planes.region_planes(disp[None], matched, labels, min_pixels=100, inlier_share=0.3, samples=32)
    assert torch.equal(plane, again)  # seeded: the same frame always gives the same planes
    reseeded, _ = planes.region_planes(disp[None], matched, labels, min_pixels=100, inlier_share=0.3, samples=32,
                                       seed=1)
    assert (reseeded[0] - truth).abs().max() < 0.01  # other triples, the same plane
    # started from least squares, the iterations settle inside the band of mismatches
    plain, _ = planes.region_planes(disp[None], matched, labels, min_pixels=100, inlier_share=0.3, samples=0)
    assert (plain[0] - truth).abs().max() > 1.0


def test_ransac_planes_skip_regions_too_small_to_fit():
    x = torch.arange(10, dtype=torch.float64)
    index = torch.tensor([1] * 8 + [2] * 2)
    coeffs = planes.ransac_planes(x / 10, (x % 3) / 10, 2 * x + 1, index, regions=3, samples=8, tolerance=0.5,
                                  min_pixels=5)
    assert torch.isnan(coeffs[0]).all() and torch.isnan(coeffs[2]).all()  # no pixels; 2 < 5 pixels
    assert torch.allclose(coeffs[1], torch.tensor([20.0, 0.0, 1.0], dtype=torch.float64), atol=1e-6)


def test_ransac_seed_chooses_the_triples():
    x = torch.arange(40, dtype=torch.float64)
    index = torch.ones(40, dtype=torch.int64)
    d = torch.where(x % 2 == 0, 2 * x + 1, -x + 30)  # two planes interleave: each seed's one triple spans another

    def once(seed):
        return planes.ransac_planes(x / 10, (x % 3) / 10, d, index, regions=2, samples=1, tolerance=0.5, seed=seed)

    draws = [once(seed)[1] for seed in range(6)]
    assert torch.equal(once(0)[1], draws[0])
    assert len({tuple(c.tolist()) for c in draws}) > 1


def test_ransac_prefers_the_plane_its_inliers_lie_closest_to():
    # 45 % of the pixels lie exactly on one plane, 55 % up to 0.8 px off another 4-10 px away: more
    # pixels lie within 1 px of the second, but the first fits its pixels far better
    gen = torch.Generator().manual_seed(5)
    n = 400
    x, y = torch.rand(n, generator=gen, dtype=torch.float64), torch.rand(n, generator=gen, dtype=torch.float64)
    exact = torch.arange(n) < 180
    d = torch.where(exact, 3 * x + 2 * y + 20, -2 * x + y + 30 + 1.6 * (torch.rand(n, generator=gen,
                                                                                   dtype=torch.float64) - 0.5))
    index = torch.ones(n, dtype=torch.int64)
    coeffs = planes.ransac_planes(x, y, d, index, regions=2, samples=64, tolerance=1.0)
    assert torch.allclose(coeffs[1], torch.tensor([3.0, 2.0, 20.0], dtype=torch.float64), atol=1e-4)
    near = ((coeffs[1, 0] * x + coeffs[1, 1] * y + coeffs[1, 2] - d).abs() < 1).sum()
    assert near == 180  # a count of inliers would have preferred a plane of the other 220 pixels


def local_scene(h=40, w=90):
    """Three regions of one slanted surface: columns 0-29 unmatched, with winners on the plane at every
    other pixel (the rest scattered), 30-59 unmatched with only scattered winners, 60-89 winners on the
    plane but half the region matched."""
    truth = slanted(h, w)
    gen = torch.Generator().manual_seed(4)
    labels = torch.full((1, h, w), 3, dtype=torch.int64)
    labels[0, :, :60] = 2
    labels[0, :, :30] = 1
    x = torch.arange(w).expand(h, w)
    noise = truth + 3 + 20 * torch.rand(h, w, generator=gen)  # winners that agree with nothing
    local = torch.where(((x % 2 == 0) & (x < 30)) | (x >= 60), truth, noise)
    matched = torch.zeros(1, h, w, dtype=torch.bool)
    matched[0, :, 60:] = x[:, 60:] % 2 == 0
    return truth, local[None], matched, labels


def test_local_planes_need_dense_agreeing_winners_in_a_region_that_did_not_match():
    truth, local, matched, labels = local_scene()
    plane, supported = planes.local_planes(local, matched, labels, min_pixels=100, inlier_share=0.3, density=0.18,
                                           max_matched=0.25, samples=32)
    assert supported[0, :, :30].all() and (plane[0, :, :30] - truth[:, :30]).abs().max() < 0.01
    assert not supported[0, :, 30:60].any()  # scattered winners make no plane
    assert not supported[0, :, 60:].any()  # half matched: its matches decide, not the winners
    _, lenient = planes.local_planes(local, matched, labels, 100, 0.3, 0.18, max_matched=0.6, samples=32)
    assert lenient[0, :, 60:].all()
    # half the winners agree: enough at density 0.18, not at 0.6
    _, strict = planes.local_planes(local, matched, labels, 100, 0.3, density=0.6, max_matched=0.25, samples=32)
    assert not strict[0, :, :30].any()
    # NaN winners (failed their left-right check) neither vote nor count as inliers
    hidden = local.clone()
    hidden[0, :, :30] = torch.where(torch.arange(30) % 2 == 0, float("nan"), local[0, :, :30])
    _, gone = planes.local_planes(hidden, matched, labels, 100, 0.3, 0.18, 0.25, samples=32)
    assert not gone[0, :, :30].any()


def test_planes_and_slopes_use_local_winners_only_where_matches_give_no_plane():
    h, w = 40, 60
    y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32), indexing="ij")
    image = torch.where(x < 30, 0.3, 0.8).expand(1, 3, h, w).contiguous()
    truth = torch.where(x < 30, 0.25 * x + 0.1 * y + 10, -0.2 * x + 40)
    # the left region matched on its plane; the right one only on two rows, too few for a plane (100)
    matched = (x < 30) & (x % 3 != 0) | (y < 2)
    # the winners before SGM: on the plane in both regions (an offset on the left shows which plane won)
    local = torch.where(x < 30, truth + 5, truth)
    filled, slope = planes.planes_and_slopes(torch.full((1, h, w), -1.0), truth[None], matched[None],
                                             planes.edge_magnitude(image, 1.0), [0.01], min_pixels=100,
                                             inlier_share=0.6, samples=32, local=local[None],
                                             local_test=(0.3, 0.18, 0.25))
    left, right = (x < 26) & ~matched, (x > 34) & ~matched
    assert (filled[0][left] - truth[left]).abs().max() < 1e-3  # its matches' plane, not the winners'
    assert (filled[0][right] - truth[right]).abs().max() < 1e-3
    assert (slope[0][(x > 34) & (x < 58)] + 0.2).abs().max() < 1e-3
    without, _ = planes.planes_and_slopes(torch.full((1, h, w), -1.0), truth[None], matched[None],
                                          planes.edge_magnitude(image, 1.0), [0.01], min_pixels=100,
                                          inlier_share=0.6, samples=32)
    assert (without[0][right] == -1).all()
    with pytest.raises(ValueError, match="local_test"):
        planes.planes_and_slopes(torch.full((1, h, w), -1.0), truth[None], matched[None],
                                 planes.edge_magnitude(image, 1.0), [0.01], 100, 0.6, 32, local[None])
