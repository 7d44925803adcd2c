"""The stages compiled with numba against the plain stage functions they replace on the CPU."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from plugins.torch_sgm import (aggregate, aggregate_numba, align, align_numba, cost, cost_numba, planes, planes_numba,
                               refine, refine_numba, select, select_numba, sgm, sgm_numba)
from plugins.torch_sgm.params import TorchSGMParams
from plugins.torch_sgm.pipeline import bgr_to_tensor, compute_disparity
from plugins.torch_sgm.synthetic import layered_scene
from synthetic_pairs import census_window

ONE_WAY = ((0, 1), (1, 1), (-1, 0))


class TestSgmNumba:
    @pytest.mark.parametrize("paths", [sgm.PATHS_4, sgm.PATHS_8, ONE_WAY])
    @pytest.mark.parametrize("shape", [(1, 9, 13, 17), (2, 5, 1, 6), (1, 4, 7, 1)])
    def test_equals_the_reference_with_one_p2_map_per_path(self, paths, shape):
        g = torch.Generator().manual_seed(3)
        volume = torch.rand(shape, generator=g)
        p2 = 0.3 + torch.rand(shape[0], len(paths), *shape[2:], generator=g)
        ref = sgm.sgm(volume, 0.1, p2, paths)
        assert torch.allclose(sgm_numba.sgm_numba(volume, 0.1, p2, paths), ref, atol=1e-5)
        # each path reads its own map: swapping them changes the sums
        if len(paths) > 1 and shape[2] > 1 and shape[3] > 1:
            assert not torch.allclose(sgm_numba.sgm_numba(volume, 0.1, p2.flip(1), paths), ref, atol=1e-3)

    @pytest.mark.parametrize("p2", [0.5, "map"])
    def test_equals_the_reference_with_a_scalar_or_one_map(self, p2):
        g = torch.Generator().manual_seed(4)
        volume = torch.rand(1, 8, 11, 14, generator=g)
        p2 = torch.rand(1, 11, 14, generator=g) + 0.2 if p2 == "map" else p2
        assert torch.allclose(sgm_numba.sgm_numba(volume, 0.08, p2, sgm.PATHS_8), sgm.sgm(volume, 0.08, p2, sgm.PATHS_8),
                              atol=1e-5)

    @pytest.mark.parametrize("shape", [(1, 11, 23, 31), (2, 5, 1, 6), (1, 4, 7, 1)])
    def test_one_thread_and_two_give_the_same_sums(self, shape):
        # on one thread the rows' paths run without a parallel region per row: the same arithmetic
        volume = torch.rand(shape, generator=torch.Generator().manual_seed(6))
        before = torch.get_num_threads()
        try:
            torch.set_num_threads(1)
            one = sgm_numba.sgm_numba(volume, 0.08, 0.6, sgm.PATHS_8)
            torch.set_num_threads(2)
            two = sgm_numba.sgm_numba(volume, 0.08, 0.6, sgm.PATHS_8)
        finally:
            torch.set_num_threads(before)
        assert torch.equal(one, two)
        assert torch.allclose(one, sgm.sgm(volume, 0.08, 0.6, sgm.PATHS_8), atol=1e-5)

    def test_a_single_disparity_is_the_cost_times_the_paths(self):
        volume = torch.rand(1, 1, 6, 7)
        assert torch.allclose(sgm_numba.sgm_numba(volume, 0.1, 0.5, sgm.PATHS_4), 4 * volume, atol=1e-6)

    def test_refuses_what_it_cannot_compute(self):
        with pytest.raises(ValueError, match="float32 CPU"):
            sgm_numba.sgm_numba(torch.rand(1, 3, 4, 5, dtype=torch.float64), 0.1, 0.5)
        with pytest.raises(ValueError, match=r"\(B, D, H, W\)"):
            sgm_numba.sgm_numba(torch.rand(3, 4, 5), 0.1, 0.5)
        assert not sgm_numba.available(torch.rand(1, 2, 3, 4, dtype=torch.float64))

    def test_runs_on_torchs_thread_count(self):
        import numba

        before = torch.get_num_threads()
        try:
            torch.set_num_threads(1)
            sgm_numba.sgm_numba(torch.rand(1, 3, 4, 5), 0.1, 0.5)
            assert numba.get_num_threads() == 1
            assert torch.get_num_threads() == 1  # and torch's own count is left as it was
        finally:
            torch.set_num_threads(before)

    def test_leaves_each_pixels_disparities_side_by_side(self):
        out = sgm_numba.sgm_numba(torch.rand(1, 5, 6, 7), 0.1, 0.5)
        assert out.shape == (1, 5, 6, 7) and select_numba.pixel_major(out) and not out.is_contiguous()


class TestAggregateNumba:
    @staticmethod
    def reference(raw, guide, radius, detail_radius, weight):
        wide = aggregate.guided_filter(guide, raw, radius, 1e-3)
        if weight is None:
            return wide
        # at radius 0 the narrow filter is raw itself, which the blend overwrites
        return aggregate.blend_by_texture(aggregate.guided_filter(guide, raw.clone(), detail_radius, 1e-3), wide, weight)

    @pytest.mark.parametrize("shape", [(1, 5, 23, 31), (2, 3, 9, 4), (1, 2, 1, 12)])
    @pytest.mark.parametrize("radius, detail_radius, weighted", [(2, 1, True), (3, 0, True), (2, 1, False)])
    def test_equals_the_reference(self, shape, radius, detail_radius, weighted):
        g = torch.Generator().manual_seed(7)
        raw = torch.rand(shape, generator=g)
        guide = torch.rand(shape[0], 1, *shape[2:], generator=g)
        weight = aggregate.texture_weight(guide, 2, 0.2) if weighted else None
        prepared = aggregate_numba.Guide(guide, radius, detail_radius, 1e-3, weight)
        ref = self.reference(raw, guide, radius, detail_radius, weight)
        assert torch.allclose(aggregate_numba.aggregate_numba(raw, prepared), ref, atol=2e-5)
        # and the narrow aggregation or the blend matter: without them it differs
        if weighted:
            assert not torch.allclose(aggregate.guided_filter(guide, raw, radius, 1e-3), ref, atol=1e-3)

    def test_writes_into_the_given_slices(self):
        raw, guide = torch.rand(1, 3, 8, 10), torch.rand(1, 1, 8, 10)
        volume = torch.zeros(1, 5, 8, 10)
        aggregate_numba.aggregate_numba(raw, aggregate_numba.Guide(guide, 2, -1, 1e-3, None), volume[:, 1:4])
        assert torch.allclose(volume[:, 1:4], aggregate.guided_filter(guide, raw, 2, 1e-3), atol=2e-5)
        assert not volume[:, 0].any() and not volume[:, 4].any()

    def test_refuses_what_it_cannot_compute(self):
        with pytest.raises(ValueError, match="radius of at least 1"):
            aggregate_numba.Guide(torch.rand(1, 1, 4, 4), 0, 1, 1e-3, None)
        with pytest.raises(ValueError, match="float32 CPU costs"):
            aggregate_numba.aggregate_numba(torch.rand(1, 2, 5, 4), aggregate_numba.Guide(torch.rand(1, 1, 4, 4), 1, 1,
                                                                                         1e-3, None))


class TestBoxMeanNumba:
    @pytest.mark.parametrize("shape", [(1, 1, 23, 31), (2, 3, 9, 4), (1, 1, 1, 12), (1, 1, 12, 1), (5, 7)])
    @pytest.mark.parametrize("radius", [1, 2, 5])
    @pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
    def test_equals_the_reference_bit_for_bit(self, shape, radius, dtype):
        # the same numbers, not nearly: the crops and the full frame must give the same maps as before
        x = torch.rand(shape, generator=torch.Generator().manual_seed(5), dtype=dtype)
        got = aggregate_numba.box_mean_numba(x, radius)
        assert got.dtype == dtype and got.shape == x.shape and torch.equal(got, cost.box_mean(x, radius))

    def test_a_view_reads_as_its_values(self):
        x = torch.rand(1, 1, 20, 30)[..., ::2, 1:]
        assert torch.equal(aggregate_numba.box_mean_numba(x, 2), cost.box_mean(x, 2))

    def test_radius_zero_returns_the_input(self):
        x = torch.rand(1, 1, 4, 4)
        assert aggregate_numba.box_mean_numba(x, 0) is x

    def test_refuses_what_it_cannot_compute(self):
        with pytest.raises(ValueError, match="float32 or float64 CPU tensor"):
            aggregate_numba.box_mean_numba(torch.ones(4, 4, dtype=torch.int32), 1)


class TestDirectBoxSums:
    @pytest.mark.parametrize("shape", [(23, 31), (3, 2), (1, 12), (12, 1)])
    @pytest.mark.parametrize("radius", [1, 2])
    def test_equals_the_running_sums(self, shape, radius):
        rng = np.random.default_rng(3)
        first, second = (rng.random(shape).astype(np.float32) for _ in range(2))
        want = [np.empty(shape, np.float32) for _ in range(2)]
        aggregate_numba.box_sums(first, second, radius, np.empty((2, shape[1])), *want)
        got = [np.full(shape, np.nan, np.float32) for _ in range(2)]
        # scratch wider than needed, and not zeroed: the margins are its own business
        aggregate_numba.direct_box_sums(first, second, radius, np.full((2, shape[1] + 2 * radius + 3), 7.0, np.float32),
                                        *got)
        for g, w in zip(got, want):
            np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
        # a corner's window is cut to the image: (r + 1)^2 pixels where both sides allow
        if min(shape) > radius:
            assert got[0][0, 0] == pytest.approx(first[:radius + 1, :radius + 1].sum(), rel=1e-6)


class TestResampleRowsNumba:
    def test_equals_the_reference(self):
        g = torch.Generator().manual_seed(4)
        image = torch.rand(2, 3, 30, 41, generator=g)
        ys, xs = torch.meshgrid(torch.arange(30.0), torch.arange(41.0), indexing="ij")
        field = torch.stack([0.3 + 0.5 * xs / 41 - 0.4 * ys / 30, -1.2 + 0.1 * xs * ys / 1230])
        field[0, :4, :6] = 0.0  # whole rows: the tap at the sample itself
        field[1, -3:] = 2.5  # past the bottom border: rows clamped
        out = align_numba.resample_rows_numba(image, field)
        assert torch.allclose(out, align.resample_rows(image, field), atol=1e-5)
        assert torch.equal(out[0, :, :4, :6], image[0, :, :4, :6])

    def test_refuses_what_it_cannot_compute(self):
        with pytest.raises(ValueError, match="float32 CPU image"):
            align_numba.resample_rows_numba(torch.rand(1, 3, 4, 5).double(), torch.zeros(1, 4, 5))
        with pytest.raises(ValueError, match=r"\(B, H, W\) offsets"):
            align_numba.resample_rows_numba(torch.rand(1, 3, 4, 5), torch.zeros(1, 4, 6))


class TestVerticalOffsetsNumba:
    def test_equals_the_reference(self):
        left, right, gt, _ = layered_scene(48, 80, seed=5)
        l_t, r_t = bgr_to_tensor(left, torch.device("cpu")), bgr_to_tensor(right, torch.device("cpu"))
        r_t = align.resample_rows(r_t, torch.full((1, 48, 80), 0.35))  # rows to find
        first = torch.from_numpy(gt).float()[None].round()  # a first disparity a pixel off at most
        ref_dy, ref_eigen = align.vertical_offsets(l_t, r_t, first, 3)
        dy, eigen = align_numba.vertical_offsets_numba(l_t, r_t, first, 3)
        assert torch.equal(eigen, ref_eigen)
        assert (dy - ref_dy).abs().max() < 1e-3  # window sums in float64 against torch's float32 cumulative sums
        textured = ref_eigen > ref_eigen.median()
        assert dy[textured].median() == pytest.approx(-0.35, abs=0.1)  # and they found the offset


class TestCheckedWinnersNumba:
    @staticmethod
    def same(a, b):
        return torch.equal(a.nan_to_num(-99.0), b.nan_to_num(-99.0))

    @pytest.mark.parametrize("order", ["pixel-major", "cost volume"])
    @pytest.mark.parametrize("first", [0, 3, -2])
    def test_equals_the_reference_ties_and_nan_included(self, order, first):
        g = torch.Generator().manual_seed(5)
        memory = torch.randint(0, 4, (2, 7, 19, 6), generator=g).float()  # few values: many ties
        memory += 0.25 * torch.rand(memory.shape, generator=g) * (torch.rand(memory.shape, generator=g) > 0.5)
        memory[0, 2, 5, 1] = float("nan")
        volume = memory.permute(0, 3, 1, 2) if order == "pixel-major" else memory.permute(0, 3, 1, 2).contiguous()
        assert select_numba.pixel_major(volume) == (order == "pixel-major")
        disparities = list(range(first, first + 6))
        ref = select.checked_winners(volume.contiguous(), disparities, 1.0)
        got = select_numba.checked_winners_numba(volume, disparities, 1.0)
        for name, a, b in zip(("disparity", "index", "right view", "consistent"), got, ref):
            assert a.dtype == b.dtype and self.same(a, b), name
        assert 0.2 < got[3].float().mean() < 0.9  # the check passes some pixels and fails others

    @pytest.mark.parametrize("order", ["pixel-major", "cost volume"])
    def test_disparities_beyond_the_image_land_nowhere(self, order):
        volume = torch.rand(1, 9, 3, 4).permute(0, 3, 1, 2)  # 4 disparities, 9 columns
        volume = volume if order == "pixel-major" else volume.contiguous()
        _, _, right, consistent = select_numba.checked_winners_numba(volume, [20, 21, 22, 23], 1.0)
        assert right.isnan().all() and not consistent.any()

    def test_refuses_what_it_cannot_compute(self):
        with pytest.raises(ValueError, match="float32 CPU"):
            select_numba.checked_winners_numba(torch.rand(1, 2, 3, 4, dtype=torch.float64), [0, 1], 1.0)


class TestUniqueMinimumNumba:
    @pytest.mark.parametrize("order", ["pixel-major", "cost volume"])
    @pytest.mark.parametrize("depth", [7, 21])  # fewer disparities than the eight minima taken in turn, and more
    def test_equals_the_reference_ties_nan_and_range_ends_included(self, order, depth):
        g = torch.Generator().manual_seed(6)
        memory = torch.randint(1, 6, (2, 5, 9, depth), generator=g).float()  # (B, H, W, D): ties and equal seconds
        memory[1, 3, 4, 5] = float("nan")
        memory[1, 2, 2, depth - 2] = float("nan")
        volume = memory.permute(0, 3, 1, 2) if order == "pixel-major" else memory.permute(0, 3, 1, 2).contiguous()
        index = volume.min(1).indices
        index[0, 0, 0], index[0, 0, 1] = 0, volume.shape[1] - 1  # winners at both ends of the range
        before = volume.clone()
        for ratio in (0.0, 0.3):
            ref = select.unique_minimum(volume.clone(), index, ratio)
            assert torch.equal(select_numba.unique_minimum_numba(volume, index, ratio), ref)
        assert torch.equal(volume.nan_to_num(-1), before.nan_to_num(-1))  # left as it was

    def test_a_winner_whose_neighbours_are_the_whole_range_has_no_second(self):
        volume = torch.rand(1, 3, 4, 5)
        index = torch.ones(1, 4, 5, dtype=torch.int64)
        assert select_numba.unique_minimum_numba(volume, index, 0.3).all()
        assert torch.equal(select.unique_minimum(volume.clone(), index, 0.3), torch.ones(1, 4, 5, dtype=torch.bool))

    def test_refuses_what_it_cannot_compute(self):
        with pytest.raises(ValueError, match="float32 CPU"):
            select_numba.unique_minimum_numba(torch.rand(1, 4, 3, 2), torch.zeros(1, 2, 3, dtype=torch.int64), 0.3)


class TestLocalPlaneFitNumba:
    def scene(self, seed=1, width=64):
        left, _, gt, _ = layered_scene(40, width, seed=seed)
        image = bgr_to_tensor(left, torch.device("cpu"))
        g = torch.Generator().manual_seed(seed)
        disp = torch.from_numpy(gt).float()[None] + 0.4 * torch.rand(1, 40, width, generator=g)
        disp[:, 5:9, 10:20] = float("nan")  # holes take no part and stay holes
        return disp, image

    @pytest.mark.parametrize("radius,sigma_colour,tolerance,width", [(3, 0.1, 1.0, 64), (1, 1e3, 0.5, 64),
                                                                     (4, 0.05, 2.0, 64), (3, 0.1, 1.0, 150)])
    def test_equals_the_reference(self, radius, sigma_colour, tolerance, width):
        # 150 columns: rows fitted in blocks (FIT_BLOCK), the last one partly filled
        disp, image = self.scene(width=width)
        ref = refine.local_plane_fit(disp, image, radius, sigma_colour, 5.0, tolerance)
        out = refine_numba.local_plane_fit_numba(disp, image, radius, sigma_colour, 5.0, tolerance)
        assert torch.equal(torch.isfinite(out), torch.isfinite(ref))
        both = torch.isfinite(ref)
        assert torch.allclose(out[both], ref[both], atol=1e-4)
        assert (out[both] - disp[both]).abs().max() > 0.05  # it did move pixels

    def test_radius_zero_returns_the_map(self):
        disp, image = self.scene()
        assert refine_numba.local_plane_fit_numba(disp, image, 0, 0.1, 5.0) is disp

    def test_bands_of_rows_give_the_whole_images_fit(self, monkeypatch):
        disp, image = self.scene(seed=2)
        disp, image = torch.cat([disp, disp.flip(-1)]), torch.cat([image, image.flip(-1)])  # two images
        whole = refine_numba.local_plane_fit_numba(disp, image, 3, 0.1, 5.0)
        # bands of 7 rows: the pairs' weights of 24 offsets, two images of 64 columns, 8 bytes each
        monkeypatch.setattr(refine_numba, "PAIR_WEIGHT_BYTES", 24 * 2 * 64 * 8 * 7)
        banded = refine_numba.local_plane_fit_numba(disp, image, 3, 0.1, 5.0)
        assert torch.equal(banded.nan_to_num(-1), whole.nan_to_num(-1))

    def test_refuses_mismatched_shapes(self):
        disp, image = self.scene()
        with pytest.raises(ValueError, match="must match"):
            refine_numba.local_plane_fit_numba(disp[:, :-1], image, 3, 0.1, 5.0)
        with pytest.raises(ValueError, match="float32 CPU"):
            refine_numba.local_plane_fit_numba(disp.double(), image, 3, 0.1, 5.0)


class TestWeightedMedianNumba:
    def scene(self):
        left, _, gt, _ = layered_scene(40, 64, seed=3)
        g = torch.Generator().manual_seed(3)
        return torch.from_numpy(gt).float()[None] + 0.3 * torch.rand(1, 40, 64, generator=g), bgr_to_tensor(left, torch.device("cpu"))

    @pytest.mark.parametrize("radius,sigma_colour,jump", [(4, 0.1, 0.0), (4, 0.1, 1.0), (2, 1e3, 0.5)])
    def test_equals_the_reference(self, radius, sigma_colour, jump):
        disp, image = self.scene()
        ref = refine.weighted_median(disp, image, radius, sigma_colour, 5.0, jump)
        out = refine_numba.weighted_median_numba(disp, image, radius, sigma_colour, 5.0, jump)
        assert (out != ref).float().mean() < 0.002
        assert (out != disp).any()  # it did filter

    def test_radius_zero_returns_the_map(self):
        disp, image = self.scene()
        assert refine_numba.weighted_median_numba(disp, image, 0, 0.1, 5.0) is disp

    def test_refuses_mismatched_shapes(self):
        disp, image = self.scene()
        with pytest.raises(ValueError, match="must match"):
            refine_numba.weighted_median_numba(disp, image[..., :-1], 3, 0.1, 5.0)

    def test_a_map_where_nothing_matched_stays_unmatched_without_a_warning(self):
        _, image = self.scene()
        disp = torch.full((1, 40, 64), float("nan"))
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            out = refine_numba.weighted_median_numba(disp, image, 2, 0.1, 5.0, 1.0)
        assert torch.isnan(out).all()


class TestOutOfViewNumba:
    def test_equals_the_reference(self):
        left, _, gt, _ = layered_scene(40, 64, seed=4)
        image = bgr_to_tensor(left, torch.device("cpu"))
        labels = planes.edge_regions(planes.edge_magnitude(image, 1.0), 0.05)
        g = torch.Generator().manual_seed(4)
        # disparities that reach past the left border, some matched pixels of them on one region
        disp = torch.from_numpy(gt).float()[None] + 20 * torch.rand(1, 40, 64, generator=g)
        matched = torch.rand(disp.shape, generator=g) < 0.8
        ref = refine.out_of_view(disp, matched, labels)
        out = refine_numba.out_of_view_numba(disp, matched, labels)
        assert torch.equal(out, ref) and ref.any()

    def test_refuses_mismatched_shapes(self):
        disp = torch.rand(1, 4, 5)
        with pytest.raises(ValueError, match="must be the same"):
            refine_numba.out_of_view_numba(disp, torch.ones(1, 4, 4, dtype=torch.bool), torch.ones(1, 4, 5).long())


class TestPlanesAndSlopesNumba:
    @staticmethod
    def regions(seed=5):
        """Six regions (and an edge column) each on its own slanted plane, with noise, 30 % mismatches and
        70 % of the pixels matched; one region holds only mismatches, one too few matches."""
        h, w = 48, 72
        y, x = torch.meshgrid(torch.arange(h, dtype=torch.float32), torch.arange(w, dtype=torch.float32),
                              indexing="ij")
        labels = (1 + (y >= 24).long() * 3 + (x >= 24).long() + (x >= 48).long())[None]
        labels[:, :, 36] = 0
        g = torch.Generator().manual_seed(seed)
        coeffs = torch.rand(7, 3, generator=g) * torch.tensor([0.4, 0.4, 30.0]) + torch.tensor([-0.2, -0.2, 10.0])
        c = coeffs[labels]
        disp = c[..., 0] * x + c[..., 1] * y + c[..., 2] + 0.2 * torch.rand(1, h, w, generator=g)
        wrong = (torch.rand(disp.shape, generator=g) < 0.3) | (labels == 6)
        disp = torch.where(wrong, disp + 3 + 8 * torch.rand(disp.shape, generator=g), disp)
        matched = (torch.rand(disp.shape, generator=g) < 0.7) & ((labels != 3) | (x < 52))
        return disp, matched, labels

    def scene(self):
        """Two frames of ``regions``, their borders from faint to strong (each edge threshold splits fewer of
        them), one region without matches (bounded by strong edges), and winners before SGM with gaps."""
        frames = [self.regions(seed) for seed in (5, 6)]
        disp = torch.cat([f[0] for f in frames])
        labels = torch.cat([f[2] for f in frames])
        matched = torch.cat([f[1] for f in frames]) & (labels != 2)
        grey = torch.tensor([0.5, 0.30, 0.9, 0.302, 0.31, 0.34, 0.42])[labels]
        magnitude = planes.edge_magnitude(grey[:, None].expand(-1, 3, -1, -1).contiguous(), 1.0)
        g = torch.Generator().manual_seed(3)
        local = torch.where(torch.rand(disp.shape, generator=g) < 0.35, float("nan"), disp)
        return torch.where(matched, disp, torch.full_like(disp, float("nan"))), disp, matched, magnitude, local

    def arguments(self, samples, with_local, seed=1):
        filled, disp, matched, magnitude, local = self.scene()
        return (filled, disp, matched, magnitude, [0.0025 * 2 ** k for k in range(5)], 40, 0.5, samples,
                local if with_local else None, (0.3, 0.18, 0.25) if with_local else None, seed)

    @pytest.mark.parametrize("samples", [0, 32])
    @pytest.mark.parametrize("with_local", [False, True])
    def test_equals_the_reference(self, samples, with_local):
        args = self.arguments(samples, with_local)
        ref, ref_slope = planes.planes_and_slopes(*args)
        out, out_slope = planes_numba.planes_and_slopes_numba(*args)
        for got, want in ((out, ref), (out_slope, ref_slope)):
            assert torch.equal(torch.isfinite(got), torch.isfinite(want))
            assert torch.allclose(got[torch.isfinite(want)], want[torch.isfinite(want)], atol=1e-4)
        matched = args[2]
        assert torch.isfinite(out_slope).any() and (torch.isfinite(out) & ~matched).any()
        assert (~torch.isfinite(out) & ~matched).any()  # a region no threshold gives a plane stays a hole
        if with_local:  # the region without matches has a plane from the winners alone
            without, _ = planes_numba.planes_and_slopes_numba(*args[:8])
            assert (torch.isfinite(out) & ~torch.isfinite(without)).any()

    def test_the_seed_picks_the_triples(self):
        a, _ = planes_numba.planes_and_slopes_numba(*self.arguments(4, False, seed=0))
        b, _ = planes_numba.planes_and_slopes_numba(*self.arguments(4, False, seed=1))
        ref, _ = planes.planes_and_slopes(*self.arguments(4, False, seed=1))
        both = torch.isfinite(b) & torch.isfinite(a)
        assert not torch.allclose(a[both], b[both], atol=1e-4)  # four triples: another seed, other planes
        assert torch.allclose(b[torch.isfinite(ref)], ref[torch.isfinite(ref)], atol=1e-4)

    def test_refuses_what_it_cannot_compute(self):
        filled, disp, matched, magnitude, local = self.scene()
        with pytest.raises(ValueError, match="float32 CPU"):
            planes_numba.planes_and_slopes_numba(filled.double(), disp, matched, magnitude, [0.01], 40, 0.5)
        with pytest.raises(ValueError, match="must be the"):
            planes_numba.planes_and_slopes_numba(filled, disp, matched[..., :-1], magnitude, [0.01], 40, 0.5)
        with pytest.raises(ValueError, match="local_test"):
            planes_numba.planes_and_slopes_numba(filled, disp, matched, magnitude, [0.01], 40, 0.5, 32, local)


class TestEdgeMagnitudeOpencv:
    # kornia's reference pads by half its kernel, which must stay inside the image
    @pytest.mark.parametrize("sigma, shape", [(0.0, (2, 3, 23, 31)), (1.0, (2, 3, 23, 31)), (2.0, (2, 3, 23, 31)),
                                              (1.0, (1, 1, 9, 5))])
    def test_equals_the_reference(self, sigma, shape):
        image = torch.rand(shape, generator=torch.Generator().manual_seed(7))
        ref = planes.edge_magnitude(image, sigma)
        got = planes_numba.edge_magnitude_opencv(image, sigma)
        assert got.shape == ref.shape and torch.allclose(got, ref, atol=1e-6)
        # the blur is the reference's: another sigma gives other edges
        assert not torch.allclose(planes_numba.edge_magnitude_opencv(image, sigma + 0.5), ref, atol=1e-3)

    def test_refuses_what_it_cannot_compute(self):
        with pytest.raises(ValueError, match="float32 CPU"):
            planes_numba.edge_magnitude_opencv(torch.rand(1, 3, 4, 5, dtype=torch.float64), 1.0)


class TestPipelineUsesIt:
    def test_the_fast_implementation_gives_the_reference_map(self):
        """The improved preset's map with the compiled SGM (fast) and with the plain stage functions."""
        left, right, _, _ = layered_scene(48, 72, seed=2)
        fast, fast_ok = compute_disparity(left, right, 0, 24, TorchSGMParams(implementation="fast"))
        ref, ref_ok = compute_disparity(left, right, 0, 24, TorchSGMParams(implementation="reference"))
        assert (fast_ok == ref_ok).mean() > 0.995
        both = np.isfinite(fast) & np.isfinite(ref)
        assert both.mean() > 0.9
        assert (np.abs(fast[both] - ref[both]) > 0.05).mean() < 0.005



class TestCostNumba:
    @staticmethod
    def pair(shape=(1, 3, 23, 31), seed=6):
        g = torch.Generator().manual_seed(seed)
        left = torch.rand(shape, generator=g)
        return left, (left.roll(3, -1) * 0.9 + 0.05 * torch.rand(shape, generator=g)).clamp(0, 1)

    @pytest.mark.parametrize("x", [np.linspace(0, 90, 1001, dtype=np.float32), np.zeros(7, np.float32)])
    def test_the_exponential_is_that_of_the_library(self, x):
        got, bits = x.copy(), np.empty(x.shape, np.int32)
        cost_numba.exp_neg_(got, bits)
        assert np.abs(got - np.exp(-x.astype(np.float64))).max() < 4e-8

    @pytest.mark.parametrize("offsets", [cost.STAR_24, census_window(4, 3)], ids=["star", "window"])
    def test_the_features_equal_the_reference_and_the_normalised_colour_its_exact_value(self, offsets):
        left, right = self.pair((2, 3, 17, 29))
        ref, got = cost.cost_features(left, right, 3, offsets), cost_numba.cost_features_numba(left, right, 3, offsets)
        for key in ("cl", "cr", "gl", "gr"):
            assert torch.equal(got[key], ref[key]), key
        for key, image in (("zl", left), ("zr", right)):
            # torch's window sums are cumulative sums in float32; these are the float64 reference's
            assert torch.allclose(got[key].double(), cost.zero_normalise(image.double(), 3), atol=1e-5)
            assert torch.allclose(got[key], ref[key], atol=1e-3)

    @pytest.mark.parametrize("d_first, count", [(0, 8), (-4, 5), (27, 6), (40, 2)])
    @pytest.mark.parametrize("weights", [(0.1, 0.6, 0.3), (0.0, 1.0, 0.0), (0.5, 0.0, 0.5)])
    def test_the_fused_cost_equals_the_reference_inside_and_beyond_the_image(self, d_first, count, weights):
        left, right = self.pair()
        features = cost.cost_features(left, right, 3, census_window(4, 3))  # three census words
        kw = dict(w_ad=weights[0], w_census=weights[1], w_grad=weights[2], lam_ad=1.0, lam_census=6.0, lam_grad=0.02)
        ref = cost.fused_cost_chunk(features, d_first, count, **kw)
        got = cost_numba.fused_cost_numba(features, d_first, count, **kw)
        assert got.shape == ref.shape and torch.allclose(got, ref, atol=1e-6)
        # slice k is disparity d_first + k: the neighbouring disparity's slice differs (beyond the image's width
        # every column meets the right image's first, whatever the disparity)
        assert d_first >= left.shape[-1] or not torch.allclose(cost_numba.fused_cost_numba(features, d_first + 1, count, **kw), ref, atol=1e-3)

    def test_refuses_what_it_cannot_compute(self):
        left, right = self.pair()
        with pytest.raises(ValueError, match="float32 CPU pair"):
            cost_numba.cost_features_numba(left.double(), right.double(), 3)
        features = cost.cost_features(left.double(), right.double(), 3)
        assert not cost_numba.available(features)
        with pytest.raises(ValueError, match="float32 CPU features"):
            cost_numba.fused_cost_numba(features, 0, 2, w_ad=0.1, w_census=0.6, w_grad=0.3, lam_ad=1.0, lam_census=6.0,
                                        lam_grad=0.02)
