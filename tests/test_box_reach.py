"""A box off its defect: the region moved about within the box's size (core/box_reach.py)."""
import numpy as np
import pytest

from core import box_reach, box_reach_numba
from core.box_reach import MovedRegion, farthest, moved_box, moved_regions, reach

SIZE = (40.0, 30.0)  # the detection's width and height


def region_of(box: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """The central 60 % of ``box``, as the depth's region is."""
    x0, y0, x1, y1 = box
    return (x0 + 0.2 * (x1 - x0), y0 + 0.2 * (y1 - y0), x1 - 0.2 * (x1 - x0), y1 - 0.2 * (y1 - y0))


def cells_over(area: tuple[float, float, float, float], defect: tuple[float, float, float, float], depth_px: float,
               noise_px: float, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """4 px cells over ``area`` (x0, y0, x1, y1) on the surface (0), those inside ``defect`` at ``-depth_px``, each
    read with noise: offsets, sds, areas (16 px each), centres."""
    x0, y0, x1, y1 = area
    u, v = np.meshgrid(np.arange(x0 + 2, x1 - 1, 4.0), np.arange(y0 + 2, y1 - 1, 4.0))
    centres = np.stack([u.ravel(), v.ravel()], axis=1)
    on = (centres[:, 0] >= defect[0]) & (centres[:, 0] < defect[2]) & (centres[:, 1] >= defect[1]) \
        & (centres[:, 1] < defect[3])
    offsets = np.where(on, -depth_px, 0.0) + np.random.default_rng(seed).normal(0.0, noise_px, len(centres))
    return offsets, np.full(len(centres), noise_px), np.full(len(centres), 16.0), centres


TRUE_BOX = (100.0, 100.0, 140.0, 130.0)
SMALL = (12.0, 12.0)  # a narrow defect's box, whose copies moved 2-4 px hold the same 4 px cells


def small_region_off_its_pit(seed: int):
    """The region of a SMALL box half its size right of a 0.6 px pit, and ``cells_over`` its reach: region, offsets,
    sds, areas, centres."""
    region = region_of((100.0, 100.0, 112.0, 112.0))
    return (region, *cells_over(reach(region, SMALL), moved_box(region, SMALL, 0.5, 180.0), 0.6, 0.05, seed=seed))


def mean_within(offsets: np.ndarray, centres: np.ndarray, box: tuple[float, float, float, float]) -> float:
    """The mean offset of the cells whose centres lie in ``box``."""
    u, v = centres[:, 0], centres[:, 1]
    return float(np.mean(offsets[(u >= box[0]) & (u < box[2]) & (v >= box[1]) & (v < box[3])]))


class TestMovedBox:
    def test_moves_by_the_share_of_the_size_towards_the_angle(self):
        assert moved_box((0.0, 0.0, 10.0, 10.0), SIZE, 0.5, 0.0) == pytest.approx((20.0, 0.0, 30.0, 10.0))
        assert moved_box((0.0, 0.0, 10.0, 10.0), SIZE, 0.5, 90.0) == pytest.approx((0.0, 15.0, 10.0, 25.0))
        assert moved_box((0.0, 0.0, 10.0, 10.0), SIZE, 0.2, 180.0) == pytest.approx((-8.0, 0.0, 2.0, 10.0))


class TestReach:
    def test_covers_every_moved_region(self):
        region = region_of(TRUE_BOX)
        grown = reach(region, SIZE)
        for share in box_reach.SHARES:
            for angle in box_reach.ANGLES_DEG:
                x0, y0, x1, y1 = moved_box(region, SIZE, share, angle)
                assert grown[0] <= x0 + 1e-9 and grown[1] <= y0 + 1e-9 and x1 <= grown[2] + 1e-9 \
                    and y1 <= grown[3] + 1e-9


class TestMovedRegions:
    def test_a_box_a_third_off_its_pit_finds_it_where_the_region_reads_it_short(self):
        # the box moved by a third of its size to the right of its pit, whose floor is the box's central 80 %
        off = moved_box(TRUE_BOX, SIZE, 0.35, 0.0)
        region = region_of(off)
        floor = (104.0, 103.0, 136.0, 127.0)
        offsets, sds, areas, centres = cells_over(reach(region, SIZE), floor, 0.4, 0.05, seed=0)
        in_region = (centres[:, 0] >= region[0]) & (centres[:, 0] < region[2]) & (centres[:, 1] >= region[1]) \
            & (centres[:, 1] < region[3])
        reading = float(np.mean(offsets[in_region]))
        assert -0.3 < reading < -0.1  # the region holds the plate beside the pit
        best = farthest(moved_regions(offsets, sds, areas, centres, region, SIZE), reading)
        assert best is not None
        x0, y0, x1, y1 = moved_box(region, SIZE, best.share, best.angle_deg)
        assert x0 >= floor[0] - 4 and y0 >= floor[1] - 4 and x1 <= floor[2] + 4 and y1 <= floor[3] + 4  # back on it
        assert best.offset == pytest.approx(-0.4, abs=0.05)
        assert best.z(reading) > 5

    def test_a_box_on_its_pit_reads_it_deepest(self):
        region = region_of(TRUE_BOX)
        floor = (104.0, 103.0, 136.0, 127.0)
        offsets, sds, areas, centres = cells_over(reach(region, SIZE), floor, 0.4, 0.05, seed=1)
        reading = -0.4
        best = farthest(moved_regions(offsets, sds, areas, centres, region, SIZE), reading)
        assert best is not None and best.z(reading) < 1.0

    def test_the_candidates_standing_farthest_out_with_enough_cells(self):
        region = region_of(TRUE_BOX)
        offsets, sds, areas, centres = cells_over(reach(region, SIZE), TRUE_BOX, 0.0, 0.05, seed=2)
        found = moved_regions(offsets, sds, areas, centres, region, SIZE)
        # the first CANDIDATES by their cells' mean and by their median: on a flat plate two rankings of noise
        assert box_reach.CANDIDATES < len(found) <= 2 * box_reach.CANDIDATES
        # a pit beyond the box's bottom edge: the copies moved down stand out, by either ranking
        offsets[centres[:, 1] > 128] -= 0.3
        found = moved_regions(offsets, sds, areas, centres, region, SIZE)
        assert len(found) <= 2 * box_reach.CANDIDATES
        assert all(0.0 < m.angle_deg < 180.0 and m.share >= 0.35 for m in found)
        assert farthest(found, 0.0).angle_deg in (67.5, 90.0, 112.5)
        # cells without a reading do not count: a region left with fewer than MIN_CELLS is left out
        sds[:] = np.inf
        assert moved_regions(offsets, sds, areas, centres, region, SIZE) == []

    def test_a_glint_s_cell_is_cut(self):
        off = moved_box(TRUE_BOX, SIZE, 0.35, 0.0)
        region = region_of(off)
        offsets, sds, areas, centres = cells_over(reach(region, SIZE), (0, 0, 0, 0), 0.0, 0.05, seed=3)
        # a glint matches sharply at a shift of its own: one cell does not make a moved region a defect
        glint = int(np.argmin(np.linalg.norm(centres - np.array([110.0, 115.0]), axis=1)))
        offsets[glint], sds[glint] = -1.5, 0.005
        best = farthest(moved_regions(offsets, sds, areas, centres, region, SIZE), 0.0)
        assert abs(best.offset) < 0.05

    def test_copies_holding_the_same_cells_are_read_once(self):
        # six copies hold the cells of the region's half on the pit. Read once each, the candidates are other parts
        # of the plate as well, one of them the copy back on the pit
        region, offsets, sds, areas, centres = small_region_off_its_pit(seed=5)
        found = moved_regions(offsets, sds, areas, centres, region, SMALL)
        u, v = centres[:, 0], centres[:, 1]
        held = [tuple(np.flatnonzero((u >= b[0]) & (u < b[2]) & (v >= b[1]) & (v < b[3])))
                for b in (moved_box(region, SMALL, m.share, m.angle_deg) for m in found)]
        assert len(set(held)) == len(found) >= box_reach.CANDIDATES
        best = farthest(found, mean_within(offsets, centres, region))
        assert best.angle_deg == 180.0 and best.offset == pytest.approx(-0.6, abs=0.05)

    def test_a_cell_read_the_other_way_does_not_hide_the_copy_on_the_pit(self):
        # the plate right of the box slopes away a little, and one of the pit's cells a wall's sheen reads as a bump:
        # that takes the mean of every copy over the pit back to the surface, below the copies on the slope, but not
        # their median
        region, offsets, sds, areas, centres = small_region_off_its_pit(seed=6)
        u, v = centres[:, 0], centres[:, 1]
        offsets[u > 110] -= 0.35
        pit = moved_box(region, SMALL, 0.5, 180.0)
        offsets[np.flatnonzero((u >= pit[0]) & (u < pit[2]) & (v >= pit[1]) & (v < pit[3]))[0]] = 1.1
        reading = mean_within(offsets, centres, region)
        best = farthest(moved_regions(offsets, sds, areas, centres, region, SMALL), reading)
        assert best.angle_deg == 180.0 and best.offset == pytest.approx(-0.6, abs=0.05)
        assert best.z(reading) > 5

    def test_shape_checks(self):
        offsets, sds, areas, centres = cells_over((0, 0, 32, 32), (0, 0, 0, 0), 0.0, 0.05, seed=4)
        with pytest.raises(ValueError, match="moved_regions"):
            moved_regions(offsets, sds[:-1], areas, centres, (8, 8, 24, 24), SIZE)
        with pytest.raises(ValueError, match="moved_regions"):
            moved_regions(offsets, sds, areas, centres[:, :1], (8, 8, 24, 24), SIZE)


def _numpy_copy_readings(offsets, sds, areas, usable, centres, edges):
    """The copies' cells and readings as NumPy's (copies x cells) arrays give them: the compiled kernel's reference."""
    u, v = centres[:, 0], centres[:, 1]
    inside = usable & (u >= edges[:, :1]) & (u < edges[:, 2:3]) & (v >= edges[:, 1:2]) & (v < edges[:, 3:])
    a = np.where(inside, areas, 0.0)
    total = np.maximum(a.sum(axis=1), 1e-12)
    x, s = np.where(usable, offsets, 0.0), np.where(usable, sds, 0.0)
    order = np.argsort(x)
    below = np.cumsum(a[:, order], axis=1)
    half = 0.5 * total[:, None]
    median = 0.5 * (x[order][np.argmax(below >= half, axis=1)] + x[order][np.argmax(below > half, axis=1)])
    return (inside, inside.sum(axis=1), (a * x).sum(axis=1) / total, median,
            np.sqrt((a * a * s * s).sum(axis=1)) / total)


class TestCopyReadings:
    @pytest.mark.parametrize("seed", [0, 1, 2])
    def test_equals_the_numpy_arrays(self, seed):
        region = region_of(TRUE_BOX)
        offsets, sds, areas, centres = cells_over(reach(region, SIZE), TRUE_BOX, 0.3, 0.05, seed=seed)
        rng = np.random.default_rng(seed)
        areas = rng.choice([4.0, 8.0, 16.0], len(areas))  # cells the reach's border cuts
        offsets[::5] = np.round(offsets[::5], 1)  # ties in the offsets' order
        sds[::7] = np.inf  # cells without a reading
        usable = np.isfinite(sds)
        edges = box_reach.copy_edges(region, SIZE)
        got = box_reach_numba.copy_readings(offsets, sds, areas, usable, centres, edges)
        want = _numpy_copy_readings(offsets, sds, areas, usable, centres, edges)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        for a, b in zip(got[2:], want[2:]):
            np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
        assert (got[1] >= box_reach.MIN_CELLS).sum() > len(edges) // 2

    def test_the_copies_edges_are_moved_boxs(self):
        region = region_of(TRUE_BOX)
        np.testing.assert_array_equal(box_reach.copy_edges(region, SIZE),
                                      [moved_box(region, SIZE, share, angle) for share, angle in box_reach.COPIES])

    def test_shape_checks(self):
        offsets, sds, areas, centres = cells_over((0, 0, 32, 32), (0, 0, 0, 0), 0.0, 0.05, seed=4)
        usable = np.ones(len(offsets), dtype=bool)
        with pytest.raises(ValueError, match="copy_readings: areas"):
            box_reach_numba.copy_readings(offsets, sds, areas[:-1], usable, centres, np.zeros((3, 4)))
        with pytest.raises(ValueError, match="copy_readings: centres"):
            box_reach_numba.copy_readings(offsets, sds, areas, usable, centres, np.zeros((3, 3)))


class TestFarthest:
    def test_the_one_farthest_from_the_surface_in_its_own_standard_deviations(self):
        near = MovedRegion(0.2, 0.0, -0.3, 0.01)  # 2 sd beyond a region reading -0.1
        far_but_noisy = MovedRegion(0.5, 90.0, -0.6, 0.25)  # 1 sd
        raised = MovedRegion(0.35, 45.0, 0.45, 0.01)  # a bump: farther from the surface too, 3.5 sd
        assert farthest([near, far_but_noisy], -0.1) is near
        assert farthest([near, far_but_noisy, raised], -0.1) is raised
        assert near.z(-0.1) == pytest.approx(2.0)
        assert farthest([], -0.1) is None

    def test_ranked_by_the_difference_with_the_region_whose_variance_is_given(self):
        # alone, the precise copy stands further out (3 sd against 2.6); with the region's variance of 0.04 in the
        # difference, the far one (2.25 against 1.3)
        precise = MovedRegion(0.2, 0.0, -0.4, 0.01)
        far = MovedRegion(0.5, 90.0, -1.0, 0.12)
        assert farthest([precise, far], -0.1) is precise
        assert farthest([precise, far], -0.1, 0.04) is far
        assert far.z(-0.1, 0.04) == pytest.approx(0.9 / 0.4)
