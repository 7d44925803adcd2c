"""The band of a region's cells that stands off the rest: a groove crossing its box."""
import numpy as np
import pytest

from core import band_scan, band_scan_numba, surface_fit
from core.band_scan import central_band, edge_direction


def grid(width_px: int = 64, height_px: int = 64, cell_px: int = 4) -> np.ndarray:
    """(K, 2) the centres of a region's cells, row by row."""
    v, u = np.mgrid[cell_px / 2 - 0.5 : height_px : cell_px, cell_px / 2 - 0.5 : width_px : cell_px]
    return np.stack([u.ravel(), v.ravel()], axis=1)


def groove_cells(angle_deg: float, depth_px: float, half_width_px: float, noise_px: float, seed: int,
                 size_px: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[float, float]]:
    """Cells of a square region on the surface (0) with a straight groove through its centre (offset
    ``-depth_px``), each read with noise: offsets, sds, centres, on the groove (bool), the region's centre."""
    centres = grid(size_px, size_px)
    centre = ((size_px - 1) / 2, (size_px - 1) / 2)
    a = np.deg2rad(angle_deg)
    across = -(centres[:, 0] - centre[0]) * np.sin(a) + (centres[:, 1] - centre[1]) * np.cos(a)
    on = np.abs(across) <= half_width_px
    rng = np.random.default_rng(seed)
    offsets = np.where(on, -depth_px, 0.0) + rng.normal(0.0, noise_px, len(centres))
    return offsets, np.full(len(centres), noise_px), centres, on, centre


def two_population_z(offsets: np.ndarray, on: np.ndarray, sd: float) -> float:
    """How many standard deviations the cells ``on`` stand off the rest by their means alone (each cell's sd ``sd``):
    what a band scan without the surface's terms would go by."""
    return abs(offsets[on].mean() - offsets[~on].mean()) / (sd * np.sqrt(1 / on.sum() + 1 / (~on).sum()))


class TestCentralBand:
    @pytest.mark.parametrize("angle", [20.0, 45.0, 70.0, 135.0])
    def test_finds_a_groove_across_the_region_where_single_cells_cannot(self, angle):
        # each cell's noise nearly as large as the groove's offset: no cell alone tells it
        offsets, sds, centres, on, centre = groove_cells(angle, 0.4, 6.0, 0.3, seed=int(angle))
        band = central_band(offsets, sds, centres, centre)
        assert band is not None and abs(band.z) >= 5.0
        assert min(abs(band.angle_deg - angle), 180 - abs(band.angle_deg - angle)) <= band_scan.ANGLE_STEP_DEG
        assert band.offset == pytest.approx(-0.4, abs=3 * np.sqrt(band.variance) + 0.05)
        assert abs(band.rest) < 0.1
        # most of the band's cells are the groove's
        assert (band.cells & on).sum() >= 0.7 * band.cells.sum()

    def test_a_flat_floor_has_no_band_standing_five_deviations_off(self):
        zs = []
        for seed in range(40):
            rng = np.random.default_rng(seed)
            centres = grid()
            sds = rng.uniform(0.05, 0.5, len(centres))
            band = central_band(-0.4 + rng.normal(0.0, sds), sds, centres, (31.5, 31.5))
            zs.append(0.0 if band is None else abs(band.z))
        assert max(zs) < 5.0
        # and the scan is not blind: the best of a few hundred bands does stand a few deviations off
        assert np.median(zs) > 1.0

    def test_a_bowl_is_no_groove(self):
        # a round pit's region: deepest at its centre, along every line through it, as a groove would be
        centres = grid()
        r2 = ((centres - 31.5) ** 2).sum(axis=1) / 32.0**2
        rng = np.random.default_rng(5)
        offsets = -0.6 * (1 - r2) + rng.normal(0.0, 0.03, len(r2))
        # the trap: the band along its middle row stands far beyond the rest, by their means alone
        on = np.abs(centres[:, 1] - 31.5) <= 4
        assert two_population_z(offsets, on, 0.03) > 20
        band = central_band(offsets, np.full(len(r2), 0.03), centres, (31.5, 31.5))
        assert band is not None and abs(band.z) < 5.0

    def test_a_region_across_a_pit_s_wall_is_no_groove(self):
        # the region runs from the surface on its left down the wall to the floor: its right-hand columns stand off
        centres = grid(16, 40)
        rng = np.random.default_rng(6)
        offsets = np.clip(-0.06 * (centres[:, 0] - 2.0), -0.6, 0.0) + rng.normal(0.0, 0.03, len(centres))
        right = centres[:, 0] > 10
        assert two_population_z(offsets, right, 0.03) > 20
        band = central_band(offsets, np.full(len(centres), 0.03), centres, (7.5, 19.5))
        assert band is None or abs(band.z) < 5.0

    def test_cells_scattering_beyond_their_noise_widen_the_band_s_variance(self):
        offsets, sds, centres, _, centre = groove_cells(45.0, 0.5, 6.0, 0.1, seed=1)
        quiet = central_band(offsets, sds, centres, centre)
        claimed = central_band(offsets, sds / 3, centres, centre)  # the same scatter, claimed three times finer
        # the cells' noise alone would give a ninth of the variance: their scatter keeps it (less the chance of
        # a scatter below the noise, which does not narrow it)
        assert 0.7 * quiet.variance <= claimed.variance <= quiet.variance

    def test_a_band_nearer_the_surface_than_the_rest_is_not_a_groove(self):
        # a floor at -0.5 with a glint-like band back at the surface: never the candidate
        _, sds, centres, on, centre = groove_cells(45.0, 0.5, 6.0, 0.02, seed=2)
        glint = np.where(on, 0.0, -0.5) + np.random.default_rng(3).normal(0.0, 0.02, len(on))
        band = central_band(glint, sds, centres, centre)
        assert band is None or abs(band.offset) > abs(band.rest)
        assert band is None or not (band.cells & on).sum() > 0.7 * band.cells.sum()

    def test_too_few_cells_and_cells_without_noise_figures_give_none(self):
        offsets, sds, centres, _, centre = groove_cells(45.0, 0.5, 6.0, 0.1, seed=4, size_px=16)
        assert central_band(offsets[:8], sds[:8], centres[:8], centre) is None
        assert central_band(offsets, np.full_like(sds, np.inf), centres, centre) is None

    def test_only_the_angles_asked_for_are_tried(self):
        offsets, sds, centres, on, centre = groove_cells(45.0, 0.4, 6.0, 0.3, seed=7)
        near = central_band(offsets, sds, centres, centre, angles_deg=np.array([32.5, 57.5]))
        assert near is not None and min(abs(near.angle_deg - a) for a in (32.5, 57.5)) < 1e-9
        along = central_band(offsets, sds, centres, centre, angles_deg=np.array([225.0]))  # 45 degrees, turned once
        assert along.angle_deg == pytest.approx(45.0) and abs(along.z) > abs(near.z)
        across = central_band(offsets, sds, centres, centre, angles_deg=np.array([135.0]))
        assert across is None or abs(across.z) < abs(along.z) / 2

    def test_shape_checks(self):
        with pytest.raises(ValueError, match="central_band"):
            central_band(np.zeros(5), np.ones(4), np.zeros((5, 2)), (0.0, 0.0))
        with pytest.raises(ValueError, match="central_band"):
            central_band(np.zeros(5), np.ones(5), np.zeros((5, 3)), (0.0, 0.0))


def plate_with_groove(angle_deg: float | None, wall_contrast: float, seed: int = 0, size: int = 96,
                      streaks: float = 0.0) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """A textured window (``streaks``: vertical streaks on top) with, where ``angle_deg`` is given, a groove's two
    walls through its centre, one lit and one shaded (``wall_contrast`` grey levels); its central 32 px region and
    the 12 px ring 3 px outside it, as (u, v)."""
    rng = np.random.default_rng(seed)
    image = rng.normal(0.0, 4.0, (size, size)) + streaks * rng.normal(0.0, 1.0, (1, size))
    v, u = np.mgrid[0:size, 0:size]
    c = (size - 1) / 2
    if angle_deg is not None:
        a = np.deg2rad(angle_deg)
        across = -(u - c) * np.sin(a) + (v - c) * np.cos(a)
        inside = np.abs((u - c) * np.cos(a) + (v - c) * np.sin(a)) < 18  # the groove ends in its box
        image += inside * wall_contrast * (np.exp(-0.5 * (across + 4) ** 2) - np.exp(-0.5 * (across - 4) ** 2))
    inner = (np.abs(u - c) < 16) & (np.abs(v - c) < 16)
    ring = (np.abs(u - c) < 31) & (np.abs(v - c) < 31) & ~((np.abs(u - c) < 19) & (np.abs(v - c) < 19))
    return image, (u[inner], v[inner]), (u[ring], v[ring])


def _numpy_central_band(offsets, sds, centres, centre, angles_deg=None):
    """``central_band`` from NumPy's (angles x widths x shifts x cells) arrays: the compiled scan's reference."""
    ok = np.isfinite(sds) & (sds > 0) & np.isfinite(offsets)
    if ok.sum() < 2 * band_scan.MIN_CELLS:
        return None
    x, w = offsets[ok], 1.0 / sds[ok] ** 2
    du, dv = centres[ok, 0] - centre[0], centres[ok, 1] - centre[1]
    surface = np.stack([np.ones_like(x), surface_fit.bowl(du, dv), du, dv], axis=1)
    angles = np.deg2rad(np.arange(0.0, 180.0, band_scan.ANGLE_STEP_DEG) if angles_deg is None
                        else np.asarray(angles_deg, dtype=np.float64) % 180.0)
    across = -du[None, :] * np.sin(angles)[:, None] + dv[None, :] * np.cos(angles)[:, None]
    widths, shifts = np.array(band_scan.HALF_WIDTHS_PX), np.array(band_scan.SHIFTS_PX)
    inside = np.abs(across[:, None, None, :] - shifts[None, None, :, None]) <= widths[None, :, None, None]
    n_in = inside.sum(axis=-1)
    wb = inside * w
    ws = surface * w[:, None]
    block = np.einsum("ki,kj->ij", ws, surface)
    r0 = np.einsum("ki,k->i", ws, x)
    u = np.einsum("...k,ki->...i", wb, surface)
    w_in = wb.sum(axis=-1)
    wx_in = np.einsum("...k,k->...", wb, x)
    w_all, wx_all = w.sum(), (w * x).sum()
    usable = (n_in >= band_scan.MIN_CELLS) & (x.size - n_in >= band_scan.MIN_CELLS)
    diagonal = np.sqrt(np.maximum(np.diag(block), 1e-300))
    normalised = np.linalg.det(block / np.outer(diagonal, diagonal))
    if not usable.any() or abs(normalised) <= 1e-9:
        return None
    inverse = np.linalg.inv(block)
    solved_u = np.einsum("ij,...j->...i", inverse, u)
    solved_r = inverse @ r0
    schur = w_in - np.einsum("...i,...i->...", u, solved_u)
    with np.errstate(invalid="ignore", divide="ignore"):
        usable &= np.abs(normalised * schur / w_in) > 1e-9
        step = (wx_in - np.einsum("...i,i->...", u, solved_r)) / schur
        fitted = np.dot(r0, solved_r) + step * step * schur
        scatter = np.maximum(((w * x * x).sum() - fitted) / max(x.size - 5, 1), 1.0)
        z = step / np.sqrt(scatter / schur)
        m_in, m_out = wx_in / w_in, (wx_all - wx_in) / (w_all - w_in)
        sd_out = np.sqrt(scatter / (w_all - w_in))
    direction = np.sign(m_in)
    usable &= (np.abs(m_in) > np.abs(m_out)) & (np.sign(z) == direction) & np.isfinite(z)
    usable &= m_out * direction >= -band_scan.REST_SDS * sd_out
    if not usable.any():
        return None
    best = np.unravel_index(np.argmax(np.where(usable, np.abs(z), -np.inf)), z.shape)
    cells = np.zeros(offsets.size, dtype=bool)
    cells[np.flatnonzero(ok)] = inside[best]
    a, h, s = best
    return band_scan.Band(float(np.rad2deg(angles[a])), float(widths[h]), float(shifts[s]), cells,
                          float(m_in[best]), float(m_out[best]), float(scatter[best] / w_in[best]), float(z[best]))


class TestBestBand:
    """``band_scan_numba.best_band``, through ``central_band``, against NumPy's arrays."""

    @pytest.mark.parametrize("seed", range(6))
    def test_picks_the_numpy_band(self, seed):
        rng = np.random.default_rng(seed)
        angle, half_width = rng.uniform(0, 180), rng.uniform(2, 10)
        offsets, sds, centres, _, centre = groove_cells(angle, rng.uniform(0.0, 0.5), half_width, 0.3, seed=seed,
                                                        size_px=int(rng.choice([32, 48, 64])))
        sds = sds * rng.uniform(0.5, 2.0, len(sds))
        sds[rng.random(len(sds)) < 0.1] = np.inf  # cells without a reading
        for angles in (None, angle + np.array(band_scan.EDGE_ANGLES_DEG)):
            got = central_band(offsets, sds, centres, centre, angles_deg=angles)
            want = _numpy_central_band(offsets, sds, centres, centre, angles_deg=angles)
            assert (got is None) == (want is None)
            if got is not None:
                assert (got.angle_deg, got.half_width_px, got.shift_px) == (want.angle_deg, want.half_width_px,
                                                                             want.shift_px)
                np.testing.assert_array_equal(got.cells, want.cells)
                assert (got.offset, got.rest, got.variance, got.z) == pytest.approx(
                    (want.offset, want.rest, want.variance, want.z), rel=1e-9, abs=1e-12)

    def test_shape_checks(self):
        with pytest.raises(ValueError, match="best_band: dv"):
            band_scan_numba.best_band(np.zeros(8), np.ones(8), np.ones((8, 4)), np.zeros(8), np.zeros(7), np.zeros(3),
                                      np.ones(2), np.zeros(1), np.eye(4), np.zeros(4), np.zeros(4), 1.0, 6, 3.0)
        with pytest.raises(ValueError, match="best_band: surface"):
            band_scan_numba.best_band(np.zeros(8), np.ones(8), np.ones((8, 4)), np.zeros(8), np.zeros(8), np.zeros(3),
                                      np.ones(2), np.zeros(1), np.eye(3), np.zeros(4), np.zeros(4), 1.0, 6, 3.0)


class TestEdgeDirection:
    @pytest.mark.parametrize("angle", [0.0, 30.0, 90.0, 150.0])
    def test_a_groove_s_walls_give_its_direction(self, angle):
        image, region, ring = plate_with_groove(angle, 60.0, seed=int(angle))
        edges = edge_direction(image, region, ring)
        assert min(abs(edges.angle_deg - angle), 180 - abs(edges.angle_deg - angle)) <= 3.0
        assert edges.oriented and edges.coherence > 0.5 and edges.contrast > 3.0

    def test_texture_alone_runs_no_way(self):
        edges = edge_direction(*plate_with_groove(None, 0.0, seed=1))
        assert not edges.oriented and edges.coherence < 0.3 and edges.contrast == pytest.approx(1.0, abs=0.3)

    def test_streaks_through_the_whole_plate_are_no_groove(self):
        # coherent, but the surface around the box is streaked alike: no stronger inside than out
        edges = edge_direction(*plate_with_groove(None, 0.0, seed=2, streaks=20.0))
        assert edges.coherence > 0.5 and edges.angle_deg == pytest.approx(90.0, abs=5.0)
        assert not edges.oriented

    def test_shape_checks(self):
        image, region, ring = plate_with_groove(30.0, 60.0)
        with pytest.raises(ValueError, match="edge_direction"):
            edge_direction(image[None], region, ring)
        with pytest.raises(ValueError, match="edge_direction"):
            edge_direction(image, (region[0], region[1][:-1]), ring)
        with pytest.raises(ValueError, match="edge_direction"):
            edge_direction(image, region, (ring[0][:0], ring[1][:0]))


def pit_cells(size_px: int, pit_px: int, depth_px: float, noise_px: float, seed: int
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[float, float]]:
    """Cells of a square region on the surface (0) with a square pit ``pit_px`` wide at its centre (offset
    ``-depth_px``), each read with noise: offsets, sds, areas (16 px each), centres, the region's centre."""
    centres = grid(size_px, size_px)
    centre = ((size_px - 1) / 2, (size_px - 1) / 2)
    on = np.all(np.abs(centres - centre) <= pit_px / 2, axis=1)
    rng = np.random.default_rng(seed)
    offsets = np.where(on, -depth_px, 0.0) + rng.normal(0.0, noise_px, len(centres))
    return offsets, np.full(len(centres), noise_px), np.full(len(centres), 16.0), centres, centre


class TestCentralPatch:
    def test_reads_a_pit_in_a_box_twice_its_size(self):
        offsets, sds, areas, centres, centre = pit_cells(32, 16, 0.5, 0.05, seed=0)
        patch = band_scan.central_patch(offsets, sds, areas, centres, centre, (16.0, 16.0))
        assert patch is not None and patch.cells == 16
        assert patch.delta == pytest.approx(-0.5, abs=3 * np.sqrt(patch.variance))
        # where the whole region reads a quarter of it
        assert np.mean(offsets) == pytest.approx(-0.125, abs=0.03)

    def test_a_glint_s_cell_is_cut(self):
        # a glint matches sharply (a small sd) at a shift of its own
        offsets, sds, areas, centres, centre = pit_cells(32, 16, 0.5, 0.1, seed=1)
        glint = int(np.argmin(np.linalg.norm(centres - centre, axis=1)))
        offsets[glint], sds[glint] = 1.2, 0.005
        patch = band_scan.central_patch(offsets, sds, areas, centres, centre, (16.0, 16.0))
        assert patch.delta == pytest.approx(-0.5, abs=0.15)

    def test_the_cells_count_by_their_share_of_the_region_not_their_information(self):
        # strongly textured cells (a wall's edge) reading nearer the surface than the weakly textured floor, each
        # within its noise: by information the patch would read the wall
        offsets, sds, areas, centres, centre = pit_cells(32, 16, 0.5, 0.05, seed=3)
        central = np.flatnonzero(np.all(np.abs(centres - centre) <= 8, axis=1))
        offsets[central[::2]], sds[central[::2]] = -0.45, 0.05
        offsets[central[1::2]], sds[central[1::2]] = -0.55, 0.5
        patch = band_scan.central_patch(offsets, sds, areas, centres, centre, (16.0, 16.0))
        assert patch.delta == pytest.approx(-0.5, abs=0.01)
        areas[central[1::2]] = 4.0  # the floor's cells cut by the region's border
        assert band_scan.central_patch(offsets, sds, areas, centres, centre, (16.0, 16.0)).delta == pytest.approx(
            -0.47, abs=0.01)

    def test_only_settled_cells_with_a_share_of_the_region_count(self):
        offsets, sds, areas, centres, centre = pit_cells(32, 16, 0.5, 0.05, seed=2)
        central = np.flatnonzero(np.all(np.abs(centres - centre) <= 8, axis=1))
        sds[central[:10]] = np.inf
        areas[central[10:13]] = 0.0
        patch = band_scan.central_patch(offsets, sds, areas, centres, centre, (16.0, 16.0))
        assert patch.cells == 3
        sds[central[13]] = np.inf
        assert band_scan.central_patch(offsets, sds, areas, centres, centre, (16.0, 16.0)) is None

    def test_shape_checks(self):
        offsets, sds, areas, centres, centre = pit_cells(32, 16, 0.5, 0.05, seed=0)
        with pytest.raises(ValueError, match="central_patch"):
            band_scan.central_patch(offsets, sds, areas[:-1], centres, centre, (16.0, 16.0))
        with pytest.raises(ValueError, match="central_patch"):
            band_scan.central_patch(offsets, sds, areas, centres[:, :1], centre, (16.0, 16.0))
