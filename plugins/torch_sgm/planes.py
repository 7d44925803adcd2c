"""Slanted-plane filling: regions of the left image bounded by its colour edges, one robust plane per
region fitted to the region's matched disparities, and that plane for the region's unmatched pixels.

Row-wise filling copies a neighbouring disparity, which is right for a fronto-parallel background but
wrong across a large textureless slanted surface (a wall, a tabletop), exactly where matching fails
most. Such a surface is one region between colour edges, and the pixels that did match on it
describe its plane.
"""
from __future__ import annotations

import cv2
import kornia
import numpy as np
import torch

# x and y enter the fit in hundreds of pixels, so that the normal equations stay well conditioned
_COORD_SCALE = 100.0
# Tukey's biweight radius per iteration, in disparity pixels: wide first so a bad start cannot lock in
_TUKEY_RADII = (8.0, 4.0, 8.0 / 3.0, 2.0, 2.0, 2.0)
# after a RANSAC start the plane is already near the majority; the iterations only refine it
_RANSAC_RADIUS = 3.0
_TUKEY_RADII_AFTER_RANSAC = (2.0, 2.0, 2.0)
_HYPOTHESES_PER_STEP = 16  # RANSAC hypotheses scored at once: bounds the (pixels x hypotheses) buffer
_FIT_PIXELS = 65536  # matched pixels a frame's planes are fitted to
_SUPPORT_PX = 1.0  # disparity px within which a pixel supports its region's plane
_VOTERS = 32768  # matched pixels that score the hypotheses; more only refine a count that needs no precision


def edge_magnitude(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """(B, 3, H, W) image in [0, 1] -> (B, H, W): the largest normalised Sobel gradient magnitude over
    the channels, after a Gaussian blur of ``sigma`` pixels (0 = none) that keeps sensor noise from
    breaking a flat surface into pieces."""
    size = 2 * int(round(4 * sigma)) + 1
    blurred = kornia.filters.gaussian_blur2d(image, (size, size), (sigma, sigma)) if sigma > 0 else image
    gradient = kornia.filters.spatial_gradient(blurred, normalized=True)  # (B, 3, 2, H, W)
    return gradient.pow(2).sum(2).sqrt().amax(1)


def edge_regions(magnitude: torch.Tensor, threshold: float) -> torch.Tensor:
    """(B, H, W) ``edge_magnitude`` -> (B, H, W) int64 region labels, 0 on edge pixels (magnitude above
    ``threshold``). Regions are the 4-connected groups of the other pixels, numbered from 1 across the
    whole batch so that no two images share a label."""
    labels, _ = connected_regions((magnitude <= threshold).cpu().numpy())
    return torch.from_numpy(labels.astype(np.int64)).to(magnitude.device)


def connected_regions(inner: np.ndarray) -> tuple[np.ndarray, int]:
    """(B, H, W) bool -> (B, H, W) int32 labels of the 4-connected groups of True pixels, numbered from 1 across
    the batch (0 elsewhere), and the number of labels with 0."""
    # connected-component labelling is a sequential union-find; OpenCV's does it in milliseconds
    labels = np.zeros(inner.shape, np.int32)
    offset = 0
    for b in range(inner.shape[0]):
        count, lab = cv2.connectedComponents(inner[b].astype(np.uint8), connectivity=4, ltype=cv2.CV_32S)
        labels[b] = lab
        if offset:
            labels[b][lab > 0] += offset
        offset += count - 1
    return labels, offset + 1


def ransac_planes(x: torch.Tensor, y: torch.Tensor, d: torch.Tensor, index: torch.Tensor, regions: int,
                  samples: int, tolerance: float, min_pixels: int = 3, seed: int = 0) -> torch.Tensor:
    """The plane through three matched pixels that the matched pixels of its region lie closest to,
    out of ``samples`` random triples per region (RANSAC, Fischler & Bolles 1981). Each pixel within
    ``tolerance`` of a plane votes 1 - (residual / tolerance)^2 for it, the others nothing: MSAC's
    truncated quadratic loss (Torr & Zisserman 2000) instead of a count of inliers.

    x, y, d (M,) float64 of the matched pixels, index (M,) int64 their region -> (regions, 3) float64
    coefficients of d = a x + b y + c; NaN for a region with fewer than ``min_pixels`` (at least 3)
    matched pixels. The triples come from a CPU generator seeded with ``seed``, so that a frame always
    gives the same planes, and the same triples on any device; at most ``_VOTERS`` pixels, evenly
    spread over each region, score them."""
    dev = x.device
    count = torch.bincount(index, minlength=regions)
    eligible = count >= max(min_pixels, 3)
    keep = eligible[index]
    x, y, d, index = x[keep], y[keep], d[keep], index[keep]
    best = torch.full((regions, 3), float("nan"), dtype=torch.float64, device=dev)
    if x.numel() == 0:
        return best
    order = torch.argsort(index, stable=True)
    x, y, d, index = x[order], y[order], d[order], index[order]
    start = torch.cumsum(torch.where(eligible, count, 0), 0) - torch.where(eligible, count, 0)
    ids = eligible.nonzero()[:, 0]  # (R,)
    # Drawn on the CPU: CUDA's generator gives another stream for the same seed, and with its triples
    # CUDA scored 7.90 % on Middlebury against 7.73 % with these (docs/research-log.md, On CUDA before the Triton
    # kernel).
    gen = torch.Generator().manual_seed(seed)
    draw = torch.rand(ids.numel(), samples, 3, generator=gen, dtype=torch.float64).to(dev)
    pick = start[ids, None, None] + (draw * count[ids, None, None]).long()  # (R, S, 3) into the sorted pixels
    system = torch.stack([x[pick], y[pick], torch.ones_like(x[pick])], -1)  # (R, S, 3, 3)
    coeffs, info = torch.linalg.solve_ex(system, d[pick].unsqueeze(-1))
    coeffs = coeffs[..., 0].float()
    usable = (info == 0) & torch.isfinite(coeffs).all(-1)
    step = -(-x.numel() // _VOTERS)
    # sorted by region, so every step-th pixel samples each region in proportion to its size
    vx, vy, vd = x[::step].float(), y[::step].float(), d[::step].float()
    slot = torch.searchsorted(ids, index[::step].contiguous())  # the voter's row among the R regions
    point = torch.stack([vx, vy, torch.ones_like(vx)], 1)  # (V, 3)
    votes = torch.zeros(ids.numel(), samples, device=dev)
    for first in range(0, samples, _HYPOTHESES_PER_STEP):
        block = coeffs[slot, first: first + _HYPOTHESES_PER_STEP]  # (V, s, 3)
        residual = (block * point[:, None, :]).sum(-1) - vd[:, None]
        # MSAC: an inlier's vote shrinks with its squared residual, so that of two planes with as many
        # inliers the one they lie closer to wins (a count flips between them from one draw to the next)
        vote = (1 - (residual / tolerance).pow(2)).clamp_min(0).nan_to_num(0.0)
        votes[:, first: first + _HYPOTHESES_PER_STEP].index_add_(0, slot, vote)
    votes = torch.where(usable, votes, torch.full_like(votes, -1.0))
    chosen = coeffs.gather(1, votes.argmax(1)[:, None, None].expand(-1, 1, 3))[:, 0]
    best[ids] = chosen.double()
    return best


def region_planes(disp: torch.Tensor, matched: torch.Tensor, labels: torch.Tensor, min_pixels: int,
                  inlier_share: float, tolerance: float = _SUPPORT_PX, samples: int = 0,
                  wanted: torch.Tensor | None = None, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Fit d = a x + b y + c to the matched pixels of every region by iteratively reweighted least
    squares with Tukey's biweight, so that mismatches that passed the checks do not tilt the plane.
    With ``samples`` > 0 the iterations start from ``ransac_planes`` instead of from plain least
    squares, which a region with more mismatches than matches would otherwise follow; ``seed`` seeds
    its triples.

    disp (B, H, W) float (any value where not matched), matched (B, H, W) bool, labels (B, H, W) int64
    from ``edge_regions`` -> (plane disparity (B, H, W) float, NaN where no plane was fitted;
    supported (B, H, W) bool). A region is supported when it has at least ``min_pixels`` matched
    pixels and at least ``inlier_share`` of them lie within ``tolerance`` of its plane; label 0 (edges)
    never is. With ``wanted`` (B, H, W) bool, only regions holding a wanted pixel are fitted."""
    b, h, w = disp.shape
    dev = disp.device
    index = labels.flatten()
    k = int(index.max()) + 1 if index.numel() else 1
    count = torch.bincount(index[matched.flatten()], minlength=k)
    active = count >= min_pixels
    if wanted is not None:
        active &= torch.bincount(index[wanted.flatten()], minlength=k) > 0
    active[0] = False
    # the fit sees only matched pixels of fitted regions, at most _FIT_PIXELS of them spread evenly
    # over the frame (raster order): a plane needs no more, and a textured frame is mostly matched
    at = active[index].nonzero()[:, 0]
    fit = at[matched.flatten()[at]]
    fit = fit[:: max(1, -(-fit.numel() // _FIT_PIXELS))]
    x, y = _coordinates(fit, h, w)
    d, region = disp.flatten()[fit].to(torch.float64), index[fit]
    coeffs = _robust_fit(x, y, d, region, k, samples, tolerance, seed)
    residual = coeffs[region, 0] * x + coeffs[region, 1] * y + coeffs[region, 2] - d
    inliers = torch.zeros(k, dtype=torch.float64, device=dev).index_add_(0, region, (residual.abs() < tolerance).double())
    good = active & (inliers >= inlier_share * torch.bincount(region, minlength=k))
    ax, ay = _coordinates(at, h, w)
    plane = torch.full((b * h * w,), float("nan"), dtype=disp.dtype, device=dev)
    c = coeffs[index[at]]
    plane[at] = (c[:, 0] * ax + c[:, 1] * ay + c[:, 2]).to(disp.dtype)
    return plane.view(b, h, w), good[labels.flatten()].view(b, h, w)


def _coordinates(flat: torch.Tensor, h: int, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat indices into (B, H, W) -> x, y float64 in units of ``_COORD_SCALE`` pixels."""
    return ((flat % w).to(torch.float64) / _COORD_SCALE,
            (flat.div(w, rounding_mode="floor") % h).to(torch.float64) / _COORD_SCALE)


def tukey_weight(residual: torch.Tensor, radius: float) -> torch.Tensor:
    """Tukey's biweight (1 - (r / radius)^2)^2, 0 beyond ``radius``: the weight of each residual in
    iteratively reweighted least squares. NaN residuals give NaN."""
    return (1 - (residual / radius).pow(2)).clamp_min(0).pow(2)


def _robust_fit(x: torch.Tensor, y: torch.Tensor, d: torch.Tensor, index: torch.Tensor, k: int, samples: int,
                tolerance: float, seed: int = 0) -> torch.Tensor:
    """IRLS with Tukey's biweight over the given pixels of each region -> (k, 3) float64 coefficients."""
    one = torch.ones_like(x)
    moments = torch.stack([x * x, x * y, x, y * y, y, one, x * d, y * d, d], 1)  # (M, 9)
    weight, radii = one, _TUKEY_RADII
    if samples > 0:
        start = ransac_planes(x, y, d, index, k, samples, tolerance, min_pixels=3, seed=seed)
        residual = (start[index] * torch.stack([x, y, one], 1)).sum(1) - d
        weight = tukey_weight(residual, _RANSAC_RADIUS)
        weight = torch.nan_to_num(weight, nan=0.0)  # a region too small to start from gets no plane
        radii = _TUKEY_RADII_AFTER_RANSAC
    eye = 1e-9 * torch.eye(3, dtype=torch.float64, device=x.device)
    for radius in radii + (None,):
        sums = torch.zeros(k, 9, dtype=torch.float64, device=x.device).index_add_(0, index, moments * weight[:, None])
        sxx, sxy, sx, syy, sy, s1, sxd, syd, sd = sums.unbind(1)
        normal = torch.stack([sxx, sxy, sx, sxy, syy, sy, sx, sy, s1], 1).view(k, 3, 3) + eye
        coeffs = torch.linalg.solve(normal, torch.stack([sxd, syd, sd], 1).unsqueeze(-1))[..., 0]  # (k, 3)
        if radius is not None:
            residual = (coeffs[index] * torch.stack([x, y, one], 1)).sum(1) - d
            weight = tukey_weight(residual, radius)
    return coeffs


def fill_from_planes(filled: torch.Tensor, disp: torch.Tensor, matched: torch.Tensor, image: torch.Tensor,
                     thresholds: list[float], sigma: float, min_pixels: int, inlier_share: float,
                     samples: int = 0) -> torch.Tensor:
    """Every pixel that is not ``matched`` takes the plane of its region (``region_planes``) at the
    first edge threshold, finest first, at which that region is supported; the others keep ``filled``.

    A fine threshold isolates a flat surface from faint edges but breaks textured ones into regions too
    small to fit; coarser thresholds then give the pixels left over a larger region.
    filled, disp (B, H, W) float, matched (B, H, W) bool, image (B, 3, H, W) -> (B, H, W)."""
    return planes_and_slopes(filled, disp, matched, edge_magnitude(image, sigma), thresholds, min_pixels,
                             inlier_share, samples)[0]


def planes_and_slopes(filled: torch.Tensor, disp: torch.Tensor, matched: torch.Tensor, magnitude: torch.Tensor,
                      thresholds: list[float], min_pixels: int, inlier_share: float,
                      samples: int = 0, local: torch.Tensor | None = None,
                      local_test: tuple[float, float, float] | None = None,
                      seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``fill_from_planes`` from the image's (B, H, W) ``edge_magnitude`` (which a caller that also
    needs the regions for something else computes once) and, from the same fits, (B, H, W) float: the
    horizontal slope (disparity per pixel along the row) of the plane of every pixel's region, matched
    pixels included, at the finest threshold at which a fitted region holding it is supported; NaN
    elsewhere. A row-wise filler carries a neighbour's slope into the holes next to it
    (``refine.fill_horizontal``).

    With ``local`` (B, H, W), the winners of the cost before SGM (``select.local_winners``, NaN where
    not trusted), a region that its matched pixels give no plane may take ``local_planes``' plane
    instead, ``local_test`` being its (inlier_share, density, max_matched). ``seed`` seeds RANSAC."""
    if local is not None and local_test is None:
        raise ValueError("planes_and_slopes: local winners given without their local_test")
    todo = ~matched
    slope = torch.full_like(disp, float("nan"))
    for threshold in thresholds:
        if not todo.any():
            break
        labels = edge_regions(magnitude, threshold)
        plane, supported = region_planes(disp, matched, labels, min_pixels, inlier_share, samples=samples,
                                         wanted=todo, seed=seed)
        if local is not None:
            extra, backed = local_planes(local, matched, labels, min_pixels, *local_test, samples=samples,
                                         wanted=todo & ~supported, seed=seed)
            plane = torch.where(supported, plane, extra)
            supported = supported | backed
        found = supported & ~torch.isfinite(slope)
        slope = torch.where(found, row_slope(plane, labels), slope)
        use = todo & supported
        filled = torch.where(use, plane, filled)
        todo &= ~use
    return filled, slope


def local_planes(local: torch.Tensor, matched: torch.Tensor, labels: torch.Tensor, min_pixels: int,
                 inlier_share: float, density: float, max_matched: float, samples: int = 0,
                 wanted: torch.Tensor | None = None, tolerance: float = _SUPPORT_PX,
                 seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``region_planes`` fitted to the winners of the cost before SGM (``select.local_winners``) of every
    pixel of a region, for a region where matching failed.

    Those winners are noisy: a region is supported only when at least ``inlier_share`` of its finite
    winners lie within ``tolerance`` of the plane, and those inliers cover at least ``density`` of the
    region, so that a few winners agreeing by chance do not make a plane. Where ``max_matched`` or more
    of the region's pixels matched, its matches already say what it is; a region that still has no plane
    of its own then holds several surfaces, and the winners' plane would be one of them.
    local (B, H, W) float, NaN where not trusted; matched (B, H, W) bool; labels from ``edge_regions``
    -> (plane disparity (B, H, W), NaN where not fitted; supported (B, H, W) bool)."""
    index = labels.flatten()
    k = int(index.max()) + 1 if index.numel() else 1
    size = torch.bincount(index, minlength=k).clamp_min(1).double()
    # tested before the fit, so that the large many-surface regions of a textured frame cost nothing
    unmatched = (torch.bincount(index[matched.flatten()], minlength=k) < max_matched * size)[index].view_as(matched)
    wanted = unmatched if wanted is None else wanted & unmatched
    finite = torch.isfinite(local)
    plane, supported = region_planes(local, finite, labels, min_pixels, inlier_share, tolerance, samples, wanted,
                                     seed)
    # inliers by region_planes' own criterion, but counted against the whole region
    inliers = (finite & ((local - plane).abs() < tolerance)).flatten()
    dense = torch.bincount(index[inliers], minlength=k) >= density * size
    return plane, supported & dense[index].view_as(supported)


def row_slope(plane: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """(B, H, W) plane disparity and region labels -> (B, H, W) its step to the next pixel of the row,
    or from the previous one at a region's right end; NaN for a pixel alone on its row in its region."""
    nan = torch.full_like(plane[..., :1], float("nan"))
    step = plane[..., 1:] - plane[..., :-1]
    same = labels[..., 1:] == labels[..., :-1]
    ahead = torch.cat([torch.where(same, step, nan), nan], -1)
    behind = torch.cat([nan, torch.where(same, step, nan)], -1)
    return torch.where(torch.isfinite(ahead), ahead, behind)
