"""Refinement of a left disparity map (B, H, W) float, NaN = invalid."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from plugins.torch_sgm.aggregate import guided_filter


def left_right_check(left_disp: torch.Tensor, right_disp: torch.Tensor, tolerance: float = 1.0) -> torch.Tensor:
    """Keep a left pixel only where the right image's disparity at x - d agrees within ``tolerance``.
    Occlusions and mismatches fail the check. (B, H, W) x2 -> (B, H, W) bool valid."""
    return view_mismatch(left_disp, right_disp) <= tolerance  # NaN and inf compare False


def _seen_by_right(left_disp: torch.Tensor, right_disp: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(B, H, W) x2 -> (the right image's column x - d, rounded, unclamped; the right map's value there,
    read at the nearest column inside the image). A NaN d reads column x."""
    w = left_disp.shape[-1]
    x = torch.arange(w, device=left_disp.device, dtype=left_disp.dtype)
    target = torch.round(x - left_disp.nan_to_num(0.0))
    return target, right_disp.gather(-1, target.clamp(0, w - 1).long())


def _nearest_valid_at(disp: torch.Tensor, reverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """For every pixel, the value of the nearest valid pixel to its left (or right when ``reverse``), and that
    pixel's column (int64; -1, or W when reverse, where there is none)."""
    w = disp.shape[-1]
    if reverse:
        value, column = _nearest_valid_at(disp.flip(-1), False)
        return value.flip(-1), (w - 1 - column).flip(-1)
    idx = torch.arange(w, device=disp.device).expand_as(disp)
    idx = torch.where(torch.isfinite(disp), idx, torch.full_like(idx, -1))
    last = idx.cummax(-1).values
    value = disp.gather(-1, last.clamp_min(0))
    return torch.where(last >= 0, value, torch.full_like(value, float("nan"))), last


def fill_horizontal(disp: torch.Tensor, slope: torch.Tensor | None = None) -> torch.Tensor:
    """Fill each hole from the nearest valid pixels on its row: the smaller disparity of the two sides,
    because holes after the LR check are mostly occlusions, which belong to the farther surface. A side
    that has no valid pixel gives way to the other.
    With ``slope`` (B, H, W), a side's value is carried into the hole along its surface: value + slope x
    distance, where its slope is finite (``planes.planes_and_slopes``); a slanted wall beside a hole
    goes on slanting instead of stopping at the hole's edge."""
    w = disp.shape[-1]
    x = torch.arange(w, device=disp.device).expand_as(disp)
    left, li = _nearest_valid_at(disp, False)
    right, ri = _nearest_valid_at(disp, True)
    if slope is not None:
        left = left + slope.gather(-1, li.clamp(0, w - 1)).nan_to_num(0.0) * (x - li)
        right = right - slope.gather(-1, ri.clamp(0, w - 1)).nan_to_num(0.0) * (ri - x)
    return torch.where(torch.isfinite(disp), disp, torch.fmin(left, right))


def out_of_view(disp: torch.Tensor, matched: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Matched pixels whose true match likely lies left of the right image, so that what they matched
    is a guess: (B, H, W) bool.

    A pixel at column x with disparity d sees its match at x - d; near the left border a surface with
    d > x has none, and the matcher takes some small disparity there that can pass the checks (a
    saturated wall at the border of Vintage matches 0) and then feeds the filling of the holes beside
    it. Each row is walked from the right; a matched pixel is suspect when x is less than the disparity
    of the last trusted match to its right in the same region of ``labels`` (``planes.edge_regions``),
    i.e. when that surface, carried to the pixel, would be out of view. A region boundary between them
    (a nearer object to the right) keeps the pixel: a background match beside it is plausible.
    disp (B, H, W) float, matched (B, H, W) bool, labels (B, H, W) int64."""
    b, h, w = disp.shape
    reference = torch.full((b, h), float("nan"), dtype=disp.dtype, device=disp.device)
    region = torch.full((b, h), -1, dtype=labels.dtype, device=disp.device)
    suspect = torch.zeros_like(matched)
    # sequential along the row (the reference moves only at trusted pixels), vectorised over rows
    for x in range(w - 1, -1, -1):
        here = matched[:, :, x]
        bad = here & (reference > x) & (labels[:, :, x] == region)
        suspect[:, :, x] = bad
        trusted = here & ~bad
        reference = torch.where(trusted, disp[:, :, x], reference)
        region = torch.where(trusted, labels[:, :, x], region)
    return suspect


def guided_refine(disp: torch.Tensor, guide: torch.Tensor, radius: int, eps: float) -> torch.Tensor:
    """Smooth a hole-free (B, H, W) map along the grey guide (B, 1, H, W)'s edges."""
    if radius <= 0:
        return disp
    return guided_filter(guide, disp.unsqueeze(1), radius, eps)[:, 0]


def median_filter(x: torch.Tensor, radius: int) -> torch.Tensor:
    """(B, H, W) -> (B, H, W) median over a (2r+1)^2 window ignoring NaN; NaN where all are NaN: the whole
    image at once, the reference that ``median_at`` and ``weighted_median`` with flat weights are held to."""
    k = 2 * radius + 1
    patches = F.unfold(F.pad(x.unsqueeze(1), (radius,) * 4, mode="replicate"), k)
    return patches.nanmedian(1).values.view_as(x)


def median_at(x: torch.Tensor, where: torch.Tensor, radius: int) -> torch.Tensor:
    """``median_filter`` evaluated only at the pixels in ``where`` (B, H, W) bool; the others keep their
    value. The holes after the LR check are a sixth of a frame, so this gathers their windows instead
    of unfolding the whole image (the same values: the median does not depend on their order)."""
    b, y, x_ = where.nonzero(as_tuple=True)
    if b.numel() == 0:
        return x
    k = 2 * radius + 1
    padded = F.pad(x.unsqueeze(1), (radius,) * 4, mode="replicate")[:, 0]
    dy = torch.arange(k, device=x.device).repeat_interleave(k)
    dx = torch.arange(k, device=x.device).repeat(k)
    windows = padded[b[:, None], y[:, None] + dy, x_[:, None] + dx]  # (N, k * k)
    out = x.clone()
    out[b, y, x_] = windows.nanmedian(1).values
    return out


def median_fill(disp: torch.Tensor, holes: torch.Tensor, radius: int) -> torch.Tensor:
    """Replace the pixels in ``holes`` (B, H, W) bool with the median of their window, which removes
    the horizontal streaks that row-wise filling leaves; any remaining NaN is filled the same way."""
    if radius > 0:
        disp = median_at(disp, holes, radius)
    for _ in range(32):
        missing = ~torch.isfinite(disp)
        if not missing.any():
            break
        disp = median_at(disp, missing, 4)
    return disp


_WEIGHTED_MEDIAN_PIXELS = 32768  # pixels whose windows are sorted at once: bounds the (pixels x window) buffers


def weighted_median(disp: torch.Tensor, image: torch.Tensor, radius: int, sigma_colour: float,
                    sigma_space: float, jump: float = 0.0) -> torch.Tensor:
    """Joint-bilateral weighted median of a hole-free (B, H, W) map over (2r+1)^2 windows, weighted by
    exp(-|I(q) - I(p)|^2 / sigma_colour^2 - |q - p|^2 / sigma_space^2) on the (B, C, H, W) image.

    Windowed matching costs drag a foreground disparity a few pixels over the background next to it
    (edge fattening); the pixels of that band resemble the background in colour, so where the band is
    narrower than about half the window the median weighted by colour similarity hands them back to
    it, and it moves filled values onto the colour edge as well. With both sigmas large it is the
    plain median. Only pixels whose window spans more than ``jump`` disparity pixels are filtered
    (0 = all): sorting every window costs 1.6 s per WVGA frame on one thread, and a smooth surface,
    most of a plate, has no edge to move. Returns (B, H, W)."""
    if radius <= 0:
        return disp
    k = 2 * radius + 1
    where = torch.ones_like(disp, dtype=torch.bool)
    if jump > 0:
        top = F.max_pool2d(disp.unsqueeze(1), k, 1, radius)[:, 0]
        bottom = -F.max_pool2d(-disp.unsqueeze(1), k, 1, radius)[:, 0]
        where = (top - bottom) > jump
    b, y, x = where.nonzero(as_tuple=True)
    offsets = torch.arange(k, device=disp.device)
    dy, dx = offsets.repeat_interleave(k), offsets.repeat(k)
    spatial = ((dy - radius) ** 2 + (dx - radius) ** 2).to(disp.dtype) / sigma_space ** 2  # (K,)
    padded_d = F.pad(disp.unsqueeze(1), (radius,) * 4, mode="replicate")[:, 0]
    padded_i = F.pad(image, (radius,) * 4, mode="replicate").movedim(1, -1)  # (B, H + 2r, W + 2r, C)
    out = disp.clone()
    for start in range(0, b.numel(), _WEIGHTED_MEDIAN_PIXELS):
        pb, py, px = (t[start: start + _WEIGHTED_MEDIAN_PIXELS, None] for t in (b, y, x))
        wy, wx = py + dy, px + dx  # (n, K) window positions in the padded maps
        values = padded_d[pb, wy, wx]
        colour = (padded_i[pb, wy, wx] - padded_i[pb, py + radius, px + radius]).pow(2).sum(-1)
        weight = torch.exp(-colour / sigma_colour ** 2 - spatial)
        ordered, order = values.sort(1)
        cumulative = weight.gather(1, order).cumsum(1)
        # the first sorted value at which the running weight reaches half of the window's total
        at = (cumulative < cumulative[:, -1:] / 2).sum(1, keepdim=True).clamp(max=k * k - 1)
        out[pb[:, 0], py[:, 0], px[:, 0]] = ordered.gather(1, at)[:, 0]
    return out


def local_plane_fit(disp: torch.Tensor, image: torch.Tensor, radius: int, sigma_colour: float,
                    sigma_space: float, tolerance: float = 1.0) -> torch.Tensor:
    """Each pixel's disparity replaced by the value at that pixel of the plane d = a x + b y + c fitted,
    by weighted least squares, to its (2r+1)^2 window: weighted like ``weighted_median`` by colour
    similarity and distance, and limited to neighbours within ``tolerance`` disparity pixels of the pixel.

    Winner-takes-all over an SGM volume locks disparities to near-integer values (on Middlebury far
    more matched pixels end close to a whole pixel than a uniform spread would put there), so a slanted
    surface comes out as a staircase whose steps are half a pixel off at their ends; the plane through
    the window puts them back on the slope. The tolerance keeps the neighbours across a depth edge out of the fit, and a
    fit that would move the pixel by more than ``tolerance`` is not used. NaN pixels (and the outside
    of the image) take no part; a NaN pixel stays NaN.
    disp (B, H, W), image (B, C, H, W) -> (B, H, W)."""
    if radius <= 0:
        return disp
    h, w = disp.shape[-2:]
    padded_d = F.pad(disp.unsqueeze(1), (radius,) * 4, value=float("nan"))[:, 0]
    padded_i = F.pad(image, (radius,) * 4)
    # weighted moments of (u, v, d(q) - d(p)) over the window, u and v the offset of q from p
    s1, su, sv, suu, suv, svv, sd, sud, svd = (torch.zeros_like(disp) for _ in range(9))
    for v in range(-radius, radius + 1):
        for u in range(-radius, radius + 1):
            rows, cols = slice(radius + v, radius + v + h), slice(radius + u, radius + u + w)
            rel = padded_d[:, rows, cols] - disp
            colour = (padded_i[:, :, rows, cols] - image).pow(2).sum(1)
            weight = torch.exp(-colour / sigma_colour ** 2 - (u * u + v * v) / sigma_space ** 2)
            weight = torch.where(rel.abs() <= tolerance, weight, torch.zeros_like(weight))  # NaN compares False
            rel = rel.nan_to_num(0.0)
            s1 += weight
            su += weight * u
            sv += weight * v
            suu += weight * (u * u)
            suv += weight * (u * v)
            svv += weight * (v * v)
            sd += weight * rel
            sud += weight * (u * rel)
            svd += weight * (v * rel)
    normal = torch.stack([suu, suv, su, suv, svv, sv, su, sv, s1], -1).unflatten(-1, (3, 3)).double()
    rhs = torch.stack([sud, svd, sd], -1).unsqueeze(-1).double()
    solution, info = torch.linalg.solve_ex(normal, rhs)
    shift = solution[..., 2, 0].to(disp.dtype)  # the plane at u = v = 0, relative to d(p)
    usable = (info == 0) & torch.isfinite(shift) & (shift.abs() <= tolerance)
    return torch.where(usable, disp + shift, disp)


def _shifted(disp: torch.Tensor, dy: int, dx: int) -> torch.Tensor:
    """(B, H, W) -> the value of the pixel (y + dy, x + dx) at (y, x); NaN where that lies outside."""
    h, w = disp.shape[-2:]
    out = torch.full_like(disp, float("nan"))
    if abs(dy) >= h or abs(dx) >= w:  # every such pixel lies outside (and a negative slice end would wrap)
        return out
    out[:, max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)] = \
        disp[:, max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)]
    return out


def view_mismatch(left_disp: torch.Tensor, right_disp: torch.Tensor) -> torch.Tensor:
    """|d - right_disp(x - d)| for every left pixel, inf where x - d leaves the right image or d is NaN:
    how far the two views' maps disagree about the point the left pixel sees. (B, H, W) x2 -> (B, H, W)."""
    target, seen = _seen_by_right(left_disp, right_disp)
    inside = (target >= 0) & (target <= left_disp.shape[-1] - 1) & torch.isfinite(left_disp)
    return torch.where(inside, (left_disp - seen).abs(), torch.full_like(left_disp, float("inf")))


def two_view_choice(disp: torch.Tensor, right_disp: torch.Tensor, reach: int, tolerance: float = 1.0,
                    iterations: int = 2) -> torch.Tensor:
    """Let every pixel of the left map that the right view's map contradicts take a neighbour's value
    that it confirms. disp, right_disp: (B, H, W) filled maps of the left view and of the right view (the
    pipeline run with the right image as reference), both positive. -> (B, H, W).

    A pixel whose disparity d misses the right map at x - d by more than ``tolerance`` takes, among the
    values of the pixels 2, 4, ..., ``reach`` px to its left, right, above and below that miss it by at
    most ``tolerance``, the one closest to d: the least change that the right view accepts. Taking the
    value that misses least instead was 0.07 points worse on Middlebury (docs/research-log.md, step 30): it
    jumps to another surface where a value close to d is confirmed too. Without such a value the pixel
    keeps d.
    Repeated ``iterations`` times, so that a confirmed value travels further than ``reach``. Unlike the
    left-right check on the matches, this compares the two filled maps, so it also reaches the holes and
    the edges that the filling got wrong in one view only."""
    offsets = [o for s in range(2, reach + 1, 2) for o in ((0, -s), (0, s), (-s, 0), (s, 0))]
    for _ in range(iterations):
        candidates = torch.stack([_shifted(disp, dy, dx) for dy, dx in offsets])  # (K, B, H, W)
        confirmed = torch.stack([view_mismatch(c, right_disp) <= tolerance for c in candidates])
        change = torch.where(confirmed, (candidates - disp).abs(), torch.full_like(candidates, float("inf")))
        least, best = change.min(0, keepdim=True)  # ties: the nearest offset, listed first
        take = ~(view_mismatch(disp, right_disp) <= tolerance) & torch.isfinite(least[0])
        disp = torch.where(take, candidates.gather(0, best)[0], disp)
    return disp


def right_view_at(left_disp: torch.Tensor, right_disp: torch.Tensor) -> torch.Tensor:
    """The right map read at x - d, linearly interpolated between its two neighbouring columns: the
    right view's disparity of the point each left pixel sees. NaN where x - d leaves the image or d is
    NaN. (B, H, W) x2 -> (B, H, W)."""
    w = left_disp.shape[-1]
    column = torch.arange(w, device=left_disp.device, dtype=left_disp.dtype) - left_disp
    inside = (column >= 0) & (column <= w - 1)  # NaN compares False
    column = torch.where(inside, column, torch.zeros_like(column))
    lo = column.floor().long()
    frac = column - lo
    hi = (lo + 1).clamp(max=w - 1)  # frac is 0 where lo is the last column
    value = right_disp.gather(-1, lo) * (1 - frac) + right_disp.gather(-1, hi) * frac
    return torch.where(inside, value, torch.full_like(value, float("nan")))


def two_view_average(disp: torch.Tensor, right_disp: torch.Tensor, tolerance: float = 1.0) -> torch.Tensor:
    """Where the two views' maps agree within ``tolerance`` about the point a left pixel sees, the
    mean of the two: each view's map went through its own matching and filling, so where both found
    the same surface their sub-pixel errors partly cancel. Elsewhere the left value stays.
    (B, H, W) x2 -> (B, H, W)."""
    seen = right_view_at(disp, right_disp)
    agree = (seen - disp).abs() <= tolerance  # NaN compares False
    return torch.where(agree, (disp + seen) / 2, disp)
