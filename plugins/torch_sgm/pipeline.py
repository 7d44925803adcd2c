"""The five stages put together, with every parameter in one settings model."""
from __future__ import annotations

import math

import numpy as np
import torch

from plugins.torch_sgm import (aggregate, aggregate_numba, align, align_numba, cost, cost_numba, planes, planes_numba,
                               refine, refine_numba, search, select, select_numba, sgm, sgm_numba, sgm_triton)


from plugins.torch_sgm.params import IMPROVED, TorchSGMParams  # noqa: F401  (re-exported)
from plugins.torch_sgm.stage_clock import untimed


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but CUDA is not available")
    return torch.device(name)


def bgr_to_tensor(image: np.ndarray, device: torch.device) -> torch.Tensor:
    """HxWx3 uint8 BGR -> (1, 3, H, W) float32 RGB in [0, 1]."""
    rgb = np.ascontiguousarray(image[..., ::-1])
    return torch.from_numpy(rgb).to(device).permute(2, 0, 1).unsqueeze(0).float() / 255.0


def cost_volume(left: torch.Tensor, right: torch.Tensor, disparities: list[int], p: TorchSGMParams) -> torch.Tensor:
    """Stages 1 and 2: fused cost, guided-filtered, built ``chunk_disparities`` slices at a time so
    only one chunk's temporaries exist besides the (B, D, H, W) result."""
    features = cost.cost_features(left, right, p.znorm_radius, cost.STAR_24, p.znorm_eps)
    guide = cost.to_grey(left)
    weight = texture_weight(guide, p)
    volume = torch.empty(left.shape[0], len(disparities), *left.shape[-2:], device=left.device, dtype=left.dtype)
    for start in range(0, len(disparities), p.chunk_disparities):
        chunk = disparities[start: start + p.chunk_disparities]
        raw = cost.fused_cost(left, right, chunk, w_ad=p.w_ad, w_census=p.w_census, w_grad=p.w_grad,
                              lam_ad=p.lam_ad, lam_census=p.lam_census, lam_grad=p.lam_grad,
                              znorm_radius=p.znorm_radius, features=features)
        aggregated = aggregate.guided_filter(guide, raw, p.agg_radius, p.agg_eps)
        if weight is not None:
            # at radius 0 this is raw itself, which the in-place blend may overwrite: nothing reads it after
            detail = aggregate.guided_filter(guide, raw, p.agg_detail_radius, p.agg_eps)
            aggregated = aggregate.blend_by_texture(detail, aggregated, weight)
        volume[:, start: start + len(chunk)] = aggregated
    return volume


TEXTURE_RADIUS = 2  # 5x5 windows measure how textured a pixel's neighbourhood is


def texture_weight(guide: torch.Tensor, p: TorchSGMParams) -> torch.Tensor | None:
    """``aggregate.texture_weight`` of the (B, 1, H, W) grey guide, or None with one radius everywhere (its box
    means compiled with the fast implementation on the CPU)."""
    if p.agg_detail_radius < 0:
        return None
    mean = aggregate_numba.box_mean_numba if compiled(p, guide) else cost.box_mean
    return aggregate.texture_weight(guide, TEXTURE_RADIUS, p.agg_texture, mean)


FAST_CHUNK = 8  # disparity slices per step of the fast path: its buffers stay small enough to be reused


def cost_volume_fast(left: torch.Tensor, right: torch.Tensor, disparities: list[int], p: TorchSGMParams) -> torch.Tensor:
    """``cost_volume`` (the reference) from ``cost.fused_cost_chunk`` and ``aggregate.guided_filter_fast``
    (on float32 CPU tensors ``cost_numba`` and ``aggregate_numba``): the disparities of a chunk in one strided
    view, the guide's statistics computed once."""
    features = (cost_numba.cost_features_numba if compiled(p, left, right) else cost.cost_features)(
        left, right, p.znorm_radius, cost.STAR_24, p.znorm_eps)
    guide = cost.to_grey(left)
    weight = texture_weight(guide, p)
    compiled_guide = (aggregate_numba.Guide(guide, p.agg_radius, p.agg_detail_radius, p.agg_eps, weight)
                      if compiled(p, left) and p.agg_radius > 0 else None)
    if compiled_guide is None:
        stats = aggregate.guide_statistics(guide, p.agg_radius, p.agg_eps) if p.agg_radius > 0 else None
        detail_stats = (aggregate.guide_statistics(guide, p.agg_detail_radius, p.agg_eps)
                        if weight is not None and p.agg_detail_radius > 0 else None)
    fused_cost = cost_numba.fused_cost_numba if compiled(p, left, right) else cost.fused_cost_chunk
    volume = torch.empty(left.shape[0], len(disparities), *left.shape[-2:], device=left.device, dtype=left.dtype)
    step = min(p.chunk_disparities, FAST_CHUNK)
    for start in range(0, len(disparities), step):
        count = min(step, len(disparities) - start)
        raw = fused_cost(features, disparities[start], count, w_ad=p.w_ad, w_census=p.w_census, w_grad=p.w_grad,
                         lam_ad=p.lam_ad, lam_census=p.lam_census, lam_grad=p.lam_grad)
        if compiled_guide is not None:
            aggregate_numba.aggregate_numba(raw, compiled_guide, volume[:, start: start + count])
            continue
        # the fast filter overwrites its input, so the narrow aggregation works on a copy
        detail = None if weight is None else raw.clone()
        if detail is not None and detail_stats is not None:
            detail = aggregate.guided_filter_fast(detail_stats, detail, p.agg_detail_radius)
        aggregated = raw if stats is None else aggregate.guided_filter_fast(stats, raw, p.agg_radius)
        if detail is not None:
            aggregated = aggregate.blend_by_texture(detail, aggregated, weight)
        volume[:, start: start + count] = aggregated
    return volume


def edge_strength(left: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) -> (B, H, W) normalised Sobel gradient magnitude of the grey image."""
    grey = cost.to_grey(left)
    gx = cost.horizontal_gradient(grey)
    gy = cost.horizontal_gradient(grey.transpose(-1, -2)).transpose(-1, -2)
    return torch.sqrt(gx * gx + gy * gy)[:, 0]


def disparity_range(min_disp: float, max_disp: float) -> list[int]:
    """Integer hypotheses covering min_disp <= d < max_disp."""
    return list(range(math.floor(min_disp), max(math.ceil(max_disp), math.floor(min_disp) + 1)))


def coarse_range(left: torch.Tensor, right: torch.Tensor, min_disp: float, max_disp: float,
                 p: TorchSGMParams) -> tuple[int, int] | None:
    """``search: coarse_to_fine``: the disparities ``lo <= d < hi`` that a pass over the whole range at
    1 / ``coarse_factor`` of the resolution finds occupied (see ``search``); None = search everything
    (the image is too small to shrink, or the coarse pass matched too little of it)."""
    found = narrowed_search(coarse_pass(left, right, min_disp, max_disp, p), tuple(left.shape[-2:]),
                            min_disp, max_disp, p)
    return None if found is None else found[0]


def coarse_pass(left: torch.Tensor, right: torch.Tensor, min_disp: float, max_disp: float, p: TorchSGMParams,
                ) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The matcher over the whole range at 1 / ``coarse_factor`` of the resolution, without filling:
    (B, h, w) disparity in coarse pixels (NaN where unmatched) and matched mask; None when the image is
    too small to shrink."""
    factor = p.coarse_factor
    if min(left.shape[-2:]) // factor < 8:  # before pooling: an image narrower than the factor pools to nothing
        return None
    small_l, small_r = search.downsample(left, factor), search.downsample(right, factor)
    w = small_l.shape[-1]
    lo, hi = search.coarse_bounds(min_disp, max_disp, factor, w)
    coarse = p.model_copy(update={"search": "full", "fill": "none", "align": "none"})
    return compute_tensors(small_l, small_r, lo, hi, coarse)


def narrowed_search(coarse: tuple[torch.Tensor, torch.Tensor] | None, size: tuple[int, int], min_disp: float,
                    max_disp: float, p: TorchSGMParams) -> tuple[tuple[int, int], torch.Tensor] | None:
    """``coarse_range`` from a ``coarse_pass`` and, with it, the (B, H, W) bool pixels that the coarse
    pass matched outside that range (``search.outside_range``)."""
    if coarse is None:
        return None
    disp, matched = coarse
    found = search.occupied_range(disp, matched, p.coarse_factor, p.coarse_margin, p.coarse_quantile,
                                  p.coarse_min_coverage, min_disp, max_disp)
    if found is None:
        return None
    return found, search.outside_range(disp, matched, p.coarse_factor, size, *found)


def aligned_right(left: torch.Tensor, right: torch.Tensor, coarse: tuple[torch.Tensor, torch.Tensor],
                  p: TorchSGMParams) -> torch.Tensor:
    """``align: projective``: the right image resampled along its columns by the field of
    vertical offsets measured against the left image at the coarse pass's disparities (see ``align``)."""
    h, w = left.shape[-2:]
    fast = compiled(p, left, right)
    first, matched = align.upsample_disparity(*coarse, p.coarse_factor, (h, w))
    dy, min_eigen = (align_numba.vertical_offsets_numba if fast else align.vertical_offsets)(left, right, first,
                                                                                             p.align_radius)
    coeffs = align.fit_row_field(dy, align.reliable_offsets(dy, min_eigen, matched))
    if not coeffs.any():
        return right
    resample = align_numba.resample_rows_numba if fast else align.resample_rows
    return align.quantise(resample(right, align.row_field(coeffs, h, w)))


def compute_tensors(left: torch.Tensor, right: torch.Tensor, min_disp: float, max_disp: float,
                    p: TorchSGMParams, clock=untimed) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, 3, H, W) RGB pair in [0, 1] -> (disparity (B, H, W) float32, NaN where still invalid;
    consistent (B, H, W) bool: pixels that passed the left-right check and, when on, the uniqueness test).
    ``clock`` (a ``StageClock``) is charged with each stage's time."""
    disparities = disparity_range(min_disp, max_disp)
    given_right = right  # the right view's own run aligns the left image to it, not to the aligned one
    wants_coarse = p.search == "coarse_to_fine" or p.align != "none"
    with clock("coarse pass"):
        coarse = coarse_pass(left, right, min_disp, max_disp, p) if wants_coarse else None
    if p.align != "none" and coarse is not None:
        with clock("vertical alignment"):
            right = aligned_right(left, right, coarse, p)
    with clock("coarse pass"):
        narrowed = (narrowed_search(coarse, tuple(left.shape[-2:]), min_disp, max_disp, p)
                    if p.search == "coarse_to_fine" else None)
    if narrowed is not None:
        full = disparities
        disparities = list(range(*narrowed[0]))
    fast = p.implementation == "fast"
    with clock("cost and aggregation"):
        volume = (cost_volume_fast if fast else cost_volume)(left, right, disparities, p)
    with clock("SGM"):
        paths = sgm.PATHS_8 if p.paths == 8 else sgm.PATHS_4
        if p.p2_edge == "path":
            penalty = sgm.path_p2(cost.to_grey(left)[:, 0], paths, p.p2, p.p2_alpha, p.p1)
        else:
            penalty = sgm.adaptive_p2(edge_strength(left), p.p2, p.p2_alpha, p.p1)
    with clock("winners"):
        checked = select_numba.checked_winners_numba if compiled(p, volume) else select.checked_winners
        local = (select.local_winners(volume, disparities, p.lr_tolerance, checked)
                 if p.fill != "none" and p.plane_fill and p.plane_local else None)
    with clock("SGM"):
        if compiled(p, volume):
            aggregated = sgm_numba.sgm_numba(volume, p.p1, penalty, paths)
        elif on_gpu(p, volume):
            aggregated = sgm_triton.sgm_triton(volume, p.p1, penalty, paths)
        else:
            aggregated = (sgm.sgm_fast if fast else sgm.sgm)(volume, p.p1, penalty, paths)
        del volume
    with clock("winners"):
        disp, index, _, consistent = checked(aggregated, disparities, p.lr_tolerance)
        if p.uniqueness > 0:
            unique = select_numba.unique_minimum_numba if compiled(p, aggregated) else select.unique_minimum
            consistent &= unique(aggregated, index, p.uniqueness)
        del aggregated
        if narrowed is not None:
            consistent &= ~search.at_narrowed_bound(index, len(disparities), disparities[0] > full[0],
                                                    disparities[-1] < full[-1])
            consistent &= ~narrowed[1]
    raw_disp = disp
    # the edges bound the regions of both the out-of-view check and the plane filling
    with clock("edges and out-of-view check"):
        magnitude = planes_numba.edge_magnitude_opencv if compiled(p, left) else planes.edge_magnitude
        edges = (magnitude(left, p.plane_sigma) if p.fill != "none" and (p.view_check_edge > 0 or p.plane_fill)
                 else None)
        if p.fill != "none" and p.view_check_edge > 0:
            labels = planes.edge_regions(edges, p.view_check_edge)
            suspect = (refine_numba.out_of_view_numba if compiled(p, raw_disp) else
                       through_the_cpu(refine_numba.out_of_view_numba) if on_gpu(p, raw_disp) else refine.out_of_view)
            consistent = consistent & ~suspect(raw_disp, consistent, labels)
        disp = torch.where(consistent, disp, torch.full_like(disp, float("nan")))
    if p.fill != "none":
        holes = ~consistent
        slope = None
        if p.plane_fill:
            with clock("slanted-plane filling"):
                # first, so that the holes without a plane are filled from plane pixels as well as matched ones
                thresholds = [p.plane_edge * 2 ** k for k in range(p.plane_levels)]
                args = (disp, raw_disp, consistent, edges, thresholds, p.plane_min_pixels, p.plane_inliers,
                        p.plane_samples, local,
                        (p.plane_local_inliers, p.plane_local_density, p.plane_local_max_matched), p.plane_seed)
                disp, slope = (planes_numba.planes_and_slopes_numba(*args) if compiled(p, disp)
                               else planes.planes_and_slopes(*args))
                holes = ~torch.isfinite(disp)
        with clock("row filling and medians"):
            disp = refine.fill_horizontal(disp, slope if p.fill_slope else None)
            disp = refine.median_fill(disp, holes, 0)  # the guided filter needs a hole-free map
            disp = refine.guided_refine(disp, cost.to_grey(left), p.refine_radius, p.refine_eps)
            disp = refine.median_fill(disp, holes, p.median_radius)
        with clock("weighted median"):
            median = refine_numba.weighted_median_numba if compiled(p, disp, left) else refine.weighted_median
            disp = median(disp, left, p.wmf_radius, p.wmf_sigma_colour, p.wmf_sigma_space, p.wmf_jump)
        with clock("local plane fit"):
            disp = plane_fit(disp, left, p)
    if p.two_view and p.fill != "none":
        with clock("two views"):
            right_map = right_view_map(left, given_right, min_disp, max_disp, p)
            disp = refine.two_view_choice(disp.clamp(float(min_disp), float(max_disp)), right_map, p.two_view_reach,
                                          p.lr_tolerance, p.two_view_iterations)
            # a value the choice took is a neighbour's, up to reach px away, so off a slanted surface's slope
            disp = plane_fit(disp, left, p)
            disp = refine.two_view_average(disp, right_map, p.lr_tolerance)
            # the mean mixes the two views' sub-pixel values pixel by pixel: put back on the local planes
            disp = plane_fit(disp, left, p)
    disp = disp.clamp(float(min_disp), float(max_disp))
    return disp, consistent


def compiled(p: TorchSGMParams, *tensors: torch.Tensor) -> bool:
    """Whether the stages compiled with numba (the cost and its aggregation, SGM, the out-of-view check, the
    slanted-plane filling (its fits and the bookkeeping between them), the local plane fit, the weighted
    median, the vertical alignment's offsets and resampling) and the edges from OpenCV's filters stand in for
    the torch ones: the fast implementation, on float32 CPU tensors."""
    return p.implementation == "fast" and all(sgm_numba.available(t) for t in tensors)


def on_gpu(p: TorchSGMParams, *tensors: torch.Tensor) -> bool:
    """Whether the fast implementation's CUDA kernels stand in for torch stages that step along the rows: SGM
    by ``sgm_triton``, the out-of-view check by its numba twin on a copy in the CPU's memory. In torch each
    step is a kernel launch of its own, thousands per frame."""
    return p.implementation == "fast" and all(sgm_triton.available(t) for t in tensors)


def through_the_cpu(kernel):
    """``kernel`` (a numba stage of CPU tensors, returning one tensor) for tensors on another device: its
    arguments copied to the CPU, its result back to their device."""
    def run(*tensors: torch.Tensor) -> torch.Tensor:
        return kernel(*(t.cpu() for t in tensors)).to(tensors[0].device)
    return run


def plane_fit(disp: torch.Tensor, left: torch.Tensor, p: TorchSGMParams) -> torch.Tensor:
    """``refine.local_plane_fit`` of the (B, H, W) map with the settings' radius, weights and tolerance
    (compiled on the CPU with the fast implementation)."""
    fit = refine_numba.local_plane_fit_numba if compiled(p, disp, left) else refine.local_plane_fit
    return fit(disp, left, p.fit_radius, p.fit_sigma_colour, p.fit_sigma_space, p.fit_tolerance)


def right_view_map(left: torch.Tensor, right: torch.Tensor, min_disp: float, max_disp: float,
                   p: TorchSGMParams) -> torch.Tensor:
    """The filled disparity map of the right view: the pipeline on the mirrored pair, whose left image
    is the mirrored right one, mirrored back. (B, H, W), positive disparities."""
    mirrored, _ = compute_tensors(torch.flip(right, (-1,)), torch.flip(left, (-1,)), min_disp, max_disp,
                                  p.model_copy(update={"two_view": False}))
    return torch.flip(mirrored, (-1,))


def compute_disparity(left: np.ndarray, right: np.ndarray, min_disp: float, max_disp: float,
                      params: TorchSGMParams | None = None, device: str | torch.device | None = None,
                      clock=untimed) -> tuple[np.ndarray, np.ndarray]:
    """HxWx3 uint8 BGR pair -> (HxW float32 disparity, NaN invalid; HxW bool LR-consistent mask).
    ``clock`` (a ``StageClock``) is charged with each stage's time, the images' way to and from the
    device included."""
    params = params or TorchSGMParams()
    dev = torch.device(device) if device is not None else pick_device(params.device)
    with torch.inference_mode():
        with clock("images to and from the device"):
            pair = bgr_to_tensor(left, dev), bgr_to_tensor(right, dev)
        disp, consistent = compute_tensors(*pair, min_disp, max_disp, params, clock)
        with clock("images to and from the device"):
            return disp[0].cpu().numpy().astype(np.float32), consistent[0].cpu().numpy()
