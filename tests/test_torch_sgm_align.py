"""Vertical alignment (``align``): each stage function on images with a known row offset, then the
whole pipeline on a synthetic pair whose rectification is off by a fraction of a pixel."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from plugins.torch_sgm import align
from plugins.torch_sgm.pipeline import TorchSGMParams, aligned_right, bgr_to_tensor, coarse_pass, compute_disparity
from plugins.torch_sgm.synthetic import layered_scene, texture

pytestmark = pytest.mark.usefixtures("torch_one_thread")
CPU = torch.device("cpu")


def _misaligned(right: np.ndarray, field: torch.Tensor) -> np.ndarray:
    """The right BGR image with its rows moved: pixel (x, y) shows the original at row y - field."""
    moved = align.quantise(align.resample_rows(bgr_to_tensor(right, CPU), -field))
    return np.ascontiguousarray((moved[0].permute(1, 2, 0).numpy()[..., ::-1] * 255).round().astype(np.uint8))


def test_lanczos_is_one_at_zero_and_zero_at_the_other_integers():
    t = torch.arange(-4.0, 5.0)
    assert torch.allclose(align.lanczos(t), (t == 0).float(), atol=1e-6)
    assert 0 < float(align.lanczos(torch.tensor(0.5))) < 1


def test_resample_rows_moves_by_whole_rows_exactly_and_interpolates_a_smooth_signal_sharply():
    image = torch.rand(1, 2, 12, 5)
    field = torch.full((1, 12, 5), 2.0)
    assert torch.allclose(align.resample_rows(image, field)[..., :10, :], image[..., 2:, :], atol=1e-6)
    assert torch.allclose(align.resample_rows(image, torch.zeros(1, 12, 5)), image, atol=1e-6)
    # a sinusoid of period 6 rows, sampled half a row down: bilinear would lose 13 % of its amplitude (cos 30°)
    rows = torch.arange(40.0)
    wave = torch.sin(2 * torch.pi * rows / 6).view(1, 1, 40, 1).expand(1, 1, 40, 3).contiguous()
    shifted = align.resample_rows(wave, torch.full((1, 40, 3), 0.5))[0, 0, 5:-5, 0]
    truth = torch.sin(2 * torch.pi * (rows[5:-5] + 0.5) / 6)
    assert (shifted - truth).abs().max() < 0.05


def test_vertical_offsets_recover_a_known_row_shift_at_a_known_disparity():
    rng = np.random.default_rng(4)
    tex = torch.from_numpy(texture(80, 140, rng)).permute(2, 0, 1)[None]
    left = tex[..., 10:-10]
    right = align.resample_rows(tex[..., 20:], torch.full((1, 80, 120), -0.3))  # 10 px disparity, 0.3 row
    disparity = torch.full((1, 80, 120), 10.0) + 0.8  # a first estimate almost a pixel off
    dy, min_eigen = align.vertical_offsets(left, right, disparity)
    reliable = align.reliable_offsets(dy, min_eigen, torch.ones_like(dy, dtype=torch.bool))
    reliable[:, :6] = reliable[:, -6:] = False
    assert reliable.sum() > 1000
    assert abs(float(dy[reliable].median()) - 0.3) < 0.03


def test_fit_row_field_recovers_the_field_despite_a_third_of_outliers():
    h, w = 60, 90
    truth = torch.tensor([[0.2, -0.4, 0.1, 0.6, -0.5]], dtype=torch.float64)
    field = align.row_field(truth, h, w)
    noisy = field + 0.02 * torch.randn(1, h, w, generator=torch.Generator().manual_seed(0))
    outliers = torch.rand(1, h, w, generator=torch.Generator().manual_seed(1)) < 0.33
    noisy[outliers] = 1.2
    reliable = torch.ones(1, h, w, dtype=torch.bool)
    assert torch.allclose(align.fit_row_field(noisy, reliable), truth, atol=0.03)
    # too few reliable pixels: no correction at all
    assert not align.fit_row_field(noisy, reliable & False).any()


def test_row_field_terms_are_centred_on_the_image():
    # a pure y^2 term is zero on the middle row and reaches a quarter of its coefficient at the edges
    field = align.row_field(torch.tensor([[0.0, 0.0, 0.0, 0.0, 1.0]], dtype=torch.float64), 101, 7)
    assert abs(float(field[0, 50, 3])) < 1e-4 and abs(float(field[0, 0, 0]) - 0.25) < 0.01


def test_upsample_disparity_scales_by_the_factor_and_keeps_the_matched_mask():
    disp = torch.tensor([[[2.0, float("nan")], [3.0, 3.0]]])
    matched = torch.isfinite(disp)
    up, mask = align.upsample_disparity(disp, matched, 4, (8, 8))
    assert mask[0, :4, :4].all() and not mask[0, :4, 4:].any()
    assert float(up[0, 0, 0]) == 8.0 and float(up[0, 7, 7]) == 12.0


def _bad(disp: np.ndarray, gt: np.ndarray, nonocc: np.ndarray) -> float:
    scored = nonocc[4:-4, 4:-4]
    return float((~(np.abs(disp - gt) <= 1.0))[4:-4, 4:-4][scored].mean())


def test_align_undoes_a_rectification_that_is_off_by_a_fraction_of_a_row():
    left, right, gt, nonocc = layered_scene(128, 192, seed=2)
    # 0.5 row at the top, 0.1 at the bottom: an offset that grows across the image, as a drifted calibration leaves
    ramp = torch.linspace(0.5, 0.1, 128).view(1, 128, 1).expand(1, 128, 192)
    skewed = _misaligned(right, ramp)
    params = TorchSGMParams(preset="improved", device="cpu", align="projective")
    tl, tr, ts = (bgr_to_tensor(im, CPU) for im in (left, right, skewed))
    with torch.inference_mode():
        restored = aligned_right(tl, ts, coarse_pass(tl, ts, 0, 32, params), params)
    inner = (..., slice(8, -8), slice(8, -8))
    before = (ts - tr)[inner].abs().mean()
    after = (restored - tr)[inner].abs().mean()
    assert after < before / 3
    # the synthetic texture is smooth enough to match either way; aligning must not cost accuracy
    plain = params.model_copy(update={"align": "none"})
    assert (_bad(compute_disparity(left, skewed, 0, 32, params)[0], gt, nonocc)
            <= _bad(compute_disparity(left, skewed, 0, 32, plain)[0], gt, nonocc) + 0.002)


def test_align_leaves_a_rectified_pair_as_it_is():
    left, right, gt, nonocc = layered_scene(128, 192, seed=5)
    plain = compute_disparity(left, right, 0, 32, TorchSGMParams(preset="improved", device="cpu", align="none"))[0]
    aligned = compute_disparity(left, right, 0, 32, TorchSGMParams(preset="improved", device="cpu",
                                                                   align="projective"))[0]
    assert abs(_bad(aligned, gt, nonocc) - _bad(plain, gt, nonocc)) < 0.005
    assert np.median(np.abs(aligned - plain)) < 0.05
