"""Matching costs. Images are (B, C, H, W) float in [0, 1]; cost volumes are (B, D, H, W),
slice ``k`` holding disparity ``min_disp + k``: the left pixel x is compared with the right pixel x - d."""
from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

# Eight directions at distances 1, 2 and 3: a star of 24 comparisons, one bit each.
STAR_24 = tuple((dy * s, dx * s) for s in (1, 2, 3) for dy, dx in
                ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)))


def to_grey(image: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) RGB -> (B, 1, H, W) luminance."""
    weights = image.new_tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)
    return (image * weights).sum(1, keepdim=True)


def box_mean(x: torch.Tensor, radius: int) -> torch.Tensor:
    """Mean over a (2r+1)^2 window, averaging only the pixels inside the image at the borders."""
    if radius <= 0:
        return x
    return _box_1d(_box_1d(x, radius, -1), radius, -2)


def _box_1d(x: torch.Tensor, radius: int, dim: int) -> torch.Tensor:
    """Windowed mean along one axis from a running sum: cost independent of the radius."""
    n = x.shape[dim]
    total = F.pad(torch.cumsum(x, dim), (1, 0) if dim == -1 else (0, 0, 1, 0))  # total[j]: the sum of x[:j]
    pos = torch.arange(n, device=x.device)
    hi = (pos + radius).clamp(max=n - 1) + 1
    lo = (pos - radius).clamp(min=0)
    count = (hi - lo).to(x.dtype)
    if n < 2 * radius + 1:  # every window cut by a border
        window = total.index_select(dim, hi) - total.index_select(dim, lo)
    else:
        # the window of x[p] is total[hi[p]] - total[lo[p]], taken as slices (a gather of the entries was most of
        # the time): inside, both step with p; by the left border lo is 0, by the right one hi is n
        r, part = radius, lambda t, a, b: t.narrow(dim, a, b - a)  # noqa: E731
        window = torch.empty_like(x)
        torch.sub(part(total, r + 1, 2 * r + 1), part(total, 0, 1), out=part(window, 0, r))
        torch.sub(part(total, 2 * r + 1, n + 1), part(total, 0, n - 2 * r), out=part(window, r, n - r))
        torch.sub(part(total, n, n + 1), part(total, n - 2 * r, n - r), out=part(window, n - r, n))
    return window / (count if dim == -1 else count.view(-1, 1))


def local_mean_variance(x: torch.Tensor, radius: int, mean=box_mean) -> tuple[torch.Tensor, torch.Tensor]:
    """``box_mean`` of x and the variance over the same windows (never negative), each shaped as x; ``mean``: the
    box mean to take them with (``aggregate_numba.box_mean_numba``, the same numbers compiled)."""
    m = mean(x, radius)
    return m, (mean(x * x, radius) - m * m).clamp_min(0)


def zero_normalise(image: torch.Tensor, radius: int, eps: float = 1e-3) -> torch.Tensor:
    """Subtract the local mean and divide by the local standard deviation, per channel, so that
    a gain or offset between the two cameras does not change the AD cost."""
    mean, var = local_mean_variance(image, radius)
    return (image - mean) / (var.sqrt() + eps)


def census_transform(grey: torch.Tensor, offsets=STAR_24) -> torch.Tensor:
    """(B, 1, H, W) -> (B, K, H, W) bool, bit k = neighbour at offsets[k] darker than the centre.
    Neighbours outside the image repeat the border pixel."""
    reach = max(max(abs(dy), abs(dx)) for dy, dx in offsets)
    padded = F.pad(grey, (reach,) * 4, mode="replicate")
    h, w = grey.shape[-2:]
    bits = [padded[:, 0, reach + dy: reach + dy + h, reach + dx: reach + dx + w] < grey[:, 0] for dy, dx in offsets]
    return torch.stack(bits, 1)


def horizontal_gradient(grey: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) -> (B, 1, H, W) normalised horizontal Sobel response."""
    kernel = grey.new_tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]]).view(1, 1, 3, 3) / 8.0
    return F.conv2d(F.pad(grey, (1, 1, 1, 1), mode="replicate"), kernel)


def shift_right_image(features: torch.Tensor, d: int) -> torch.Tensor:
    """Right-image features moved so that column x holds right column x - d (border replicated)."""
    if d == 0:
        return features
    w = features.shape[-1]
    if d > 0:
        edge = features[..., :1].expand(*features.shape[:-1], min(d, w))
        return torch.cat([edge, features[..., : max(w - d, 0)]], -1)[..., :w]
    edge = features[..., -1:].expand(*features.shape[:-1], min(-d, w))
    return torch.cat([features[..., min(-d, w):], edge], -1)[..., :w]


def _volume(left: torch.Tensor, right: torch.Tensor, disparities, distance) -> torch.Tensor:
    return torch.stack([distance(left, shift_right_image(right, d)) for d in disparities], 1)


BITS_PER_WORD = 30  # non-negative int32 words keep the shifts in popcount free of sign bits


def pack_bits(bits: torch.Tensor) -> torch.Tensor:
    """(B, K, H, W) bool -> (B, ceil(K / 30), H, W) int32 words, bit k of the string = bit k % 30 of word k // 30."""
    words = []
    for start in range(0, bits.shape[1], BITS_PER_WORD):
        chunk = bits[:, start: start + BITS_PER_WORD]
        # bit by bit into one word: a sum over the bit axis reduces across strided memory, 10x slower
        word = torch.zeros(chunk.shape[0], *chunk.shape[2:], dtype=torch.int32, device=bits.device)
        for k in range(chunk.shape[1]):
            word.add_(chunk[:, k], alpha=2 ** k)
        words.append(word)
    return torch.stack(words, 1)


def popcount(x: torch.Tensor) -> torch.Tensor:
    """Number of set bits of non-negative int32 values (SWAR: torch has no popcount)."""
    x = x - ((x >> 1) & 0x55555555)
    x = (x & 0x33333333) + ((x >> 2) & 0x33333333)
    x = (x + (x >> 4)) & 0x0F0F0F0F
    return (x + (x >> 8) + (x >> 16) + (x >> 24)) & 0x3F


def census_cost(left_code: torch.Tensor, right_code: torch.Tensor, disparities) -> torch.Tensor:
    """Hamming distance between packed census strings (B, n_words, H, W) int32 -> (B, D, H, W) float32 bit counts."""
    return torch.stack([popcount(left_code ^ shift_right_image(right_code, d)).sum(1).float() for d in disparities], 1)


def ad_cost(left: torch.Tensor, right: torch.Tensor, disparities) -> torch.Tensor:
    """Mean absolute difference over channels: (B, C, H, W) x2 -> (B, D, H, W)."""
    return _volume(left, right, disparities, lambda a, b: (a - b).abs().mean(1))


def gradient_cost(left_grad: torch.Tensor, right_grad: torch.Tensor, disparities) -> torch.Tensor:
    """Absolute gradient difference: (B, 1, H, W) x2 -> (B, D, H, W)."""
    return _volume(left_grad, right_grad, disparities, lambda a, b: (a - b).abs()[:, 0])


def robust(cost: torch.Tensor, lam: float) -> torch.Tensor:
    """1 - exp(-c / lambda): maps any cost to [0, 1) so that no term dominates the fusion."""
    return 1.0 - torch.exp(-cost / lam)


def fused_cost(left: torch.Tensor, right: torch.Tensor, disparities, *, w_ad: float, w_census: float,
               w_grad: float, lam_ad: float, lam_census: float, lam_grad: float, znorm_radius: int,
               features: dict | None = None, census_offsets=STAR_24, znorm_eps: float = 1e-3) -> torch.Tensor:
    """(B, 3, H, W) RGB pair -> (B, D, H, W) fused cost in [0, w_ad + w_census + w_grad).
    ``features`` (from ``cost_features``) avoids recomputing per-image work when called per chunk."""
    f = features or cost_features(left, right, znorm_radius, census_offsets, znorm_eps)
    total = torch.zeros(left.shape[0], len(disparities), *left.shape[-2:], device=left.device, dtype=left.dtype)
    if w_ad:
        total += w_ad * robust(ad_cost(f["zl"], f["zr"], disparities), lam_ad)
    if w_census:
        total += w_census * robust(census_cost(f["cl"], f["cr"], disparities), lam_census)
    if w_grad:
        total += w_grad * robust(gradient_cost(f["gl"], f["gr"], disparities), lam_grad)
    return total


def cost_features(left: torch.Tensor, right: torch.Tensor, znorm_radius: int, census_offsets=STAR_24,
                  znorm_eps: float = 1e-3) -> dict:
    """The per-image inputs of the three costs, computed once for all disparity chunks."""
    grey_l, grey_r = to_grey(left), to_grey(right)
    return {
        "zl": zero_normalise(left, znorm_radius, znorm_eps), "zr": zero_normalise(right, znorm_radius, znorm_eps),
        "cl": pack_bits(census_transform(grey_l, census_offsets)),
        "cr": pack_bits(census_transform(grey_r, census_offsets)),
        "gl": horizontal_gradient(grey_l), "gr": horizontal_gradient(grey_r),
    }


# --- Fast path -------------------------------------------------------------------------------------
# The same fused cost as ``fused_cost`` (its reference), computed for a run of consecutive
# disparities at once from a strided view of the right image's features instead of one shifted copy
# per disparity, with every step writing into a buffer of the chunk's size. Shapes as above.


def shifted_stack(features: torch.Tensor, d_first: int, count: int) -> torch.Tensor:
    """A view (no copy), (B, C, count, H, W): slice k holds ``shift_right_image(features, d_first - k)``,
    i.e. *descending* disparities d_first, d_first - 1, ... (a view can only step forwards in memory)."""
    b, c, h, w = features.shape
    d_last = d_first - count + 1
    pad_left, pad_right = max(d_first, 0), max(-d_last, 0)
    padded = _pad_columns(features, pad_left, pad_right)
    sb, sc, sh, sw = padded.stride()
    start = pad_left - d_first  # column of padded that holds right column x - d_first for x = 0
    return padded.as_strided((b, c, count, h, w), (sb, sc, sw, sh, sw), padded.storage_offset() + start * sw)


def _pad_columns(x: torch.Tensor, left: int, right: int) -> torch.Tensor:
    """Replicate padding along the last axis for any dtype (F.pad's replicate mode wants floats)."""
    parts = [x[..., :1].expand(*x.shape[:-1], left), x, x[..., -1:].expand(*x.shape[:-1], right)]
    return torch.cat([p for p in parts if p.shape[-1]], -1)


HALF_WORD = 15  # census words hold 30 bits: two 15-bit halves index one table each


@functools.lru_cache(maxsize=8)  # built once per lambda and device, not once per disparity chunk
def census_factor_table(lam: float, device=None) -> torch.Tensor:
    """exp(-popcount(i) / lam) for every 15-bit i: since exp(-(a + b) / lam) = exp(-a / lam) * exp(-b / lam),
    the robust census term of a code is the product of its halves' entries (two look-ups instead of a
    popcount, a conversion and an exponential)."""
    values = torch.arange(2 ** HALF_WORD, dtype=torch.int32, device=device)
    return torch.exp(-popcount(values).float() / lam)


def fused_cost_chunk(features: dict, d_first: int, count: int, *, w_ad: float, w_census: float, w_grad: float,
                     lam_ad: float, lam_census: float, lam_grad: float) -> torch.Tensor:
    """``fused_cost`` for disparities d_first, d_first + 1, ..., d_first + count - 1, from ``cost_features``.
    Returns (B, count, H, W) float32, equal to the reference up to float rounding.

    Works on ``sum_t w_t * exp(-c_t / lambda_t)`` (``weight``), which is ``w_ad + w_census + w_grad`` minus
    the fused cost."""
    zl, cl, gl = features["zl"], features["cl"], features["gl"]
    b, _, h, w = zl.shape
    d_top = d_first + count - 1
    shape = (b, count, h, w)
    tmp = torch.empty(shape, dtype=zl.dtype, device=zl.device)
    weight = None

    def add(term: torch.Tensor, w_term: float) -> torch.Tensor:
        return term.mul_(w_term) if weight is None else weight.add_(term, alpha=w_term)

    if w_ad:
        right = shifted_stack(features["zr"], d_top, count)
        term = torch.sub(zl[:, :1], right[:, 0], out=torch.empty_like(tmp)).abs_()
        for ch in range(1, zl.shape[1]):
            term.add_(torch.sub(zl[:, ch: ch + 1], right[:, ch], out=tmp).abs_())
        weight = add(term.mul_(-1.0 / (zl.shape[1] * lam_ad)).exp_(), w_ad)
    if w_census:
        table = census_factor_table(lam_census, zl.device)
        right = shifted_stack(features["cr"], d_top, count)
        word = torch.empty(shape, dtype=torch.int32, device=zl.device)
        low = torch.empty_like(word)
        term = torch.empty_like(tmp)
        for k in range(cl.shape[1]):
            torch.bitwise_xor(cl[:, k: k + 1], right[:, k], out=word)
            torch.bitwise_and(word, 2 ** HALF_WORD - 1, out=low)
            factor = term if k == 0 else tmp
            torch.index_select(table, 0, low.view(-1), out=factor.view(-1))
            if k > 0:
                term.mul_(factor)
            torch.index_select(table, 0, word.bitwise_right_shift_(HALF_WORD).view(-1), out=tmp.view(-1))
            term.mul_(tmp)
        del word, low
        weight = add(term, w_census)
    if w_grad:
        right = shifted_stack(features["gr"], d_top, count)
        term = torch.sub(gl, right[:, 0], out=torch.empty_like(tmp)).abs_()
        weight = add(term.mul_(-1.0 / lam_grad).exp_(), w_grad)
    if weight is None:
        return torch.zeros(shape, dtype=zl.dtype, device=zl.device)
    # sum of w * (1 - exp(-c / lambda)), in ascending disparity order
    return torch.flip(weight, (1,)).neg_().add_(w_ad + w_census + w_grad)


# Up to this radius, 2r shifted additions beat a running sum: torch.cumsum walks a row element by
# element, while each addition is one vectorised pass (1.5x faster at r = 3, the seed's radius).
SHIFTED_SUM_MAX_RADIUS = 4


def _shifted_sum_(x: torch.Tensor, radius: int, dim: int, out: torch.Tensor) -> torch.Tensor:
    """Window sums along ``dim`` into ``out`` (not ``x``) by adding the 2r shifted copies of ``x``."""
    n = x.shape[dim]
    out.copy_(x)
    for s in range(1, min(radius, n - 1) + 1):
        out.narrow(dim, s, n - s).add_(x.narrow(dim, 0, n - s))
        out.narrow(dim, 0, n - s).add_(x.narrow(dim, s, n - s))
    return out


def _box_sum_(x: torch.Tensor, radius: int, dim: int, out: torch.Tensor, work: torch.Tensor) -> torch.Tensor:
    """Window sums along ``dim`` (-1 or -2) into ``out`` from a running sum in ``work``, by slicing
    (the reference's ``index_select`` is several times slower). ``x`` is read only for the running sum,
    so ``out`` may be ``x``. Needs size >= 2 * radius + 2."""
    n, r = x.shape[dim], radius
    torch.cumsum(x, dim, out=work)
    cs = lambda a, b: work.narrow(dim, a, b - a)  # noqa: E731
    dst = lambda a, b: out.narrow(dim, a, b - a)  # noqa: E731
    torch.sub(cs(2 * r + 1, n), cs(0, n - 2 * r - 1), out=dst(r + 1, n - r))
    dst(0, r + 1).copy_(cs(r, 2 * r + 1))
    torch.sub(cs(n - 1, n), cs(n - 2 * r - 1, n - r - 1), out=dst(n - r, n))
    return out


def box_counts(h: int, w: int, radius: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(H, W): 1 / the number of in-image pixels in each (2r+1)^2 window."""
    def count(n):
        pos = torch.arange(n, device=device)
        return ((pos + radius).clamp(max=n - 1) - (pos - radius).clamp(min=0) + 1).to(dtype)
    return 1.0 / (count(h)[:, None] * count(w)[None, :])


def box_mean_fast(x: torch.Tensor, radius: int, out: torch.Tensor | None = None, work: torch.Tensor | None = None,
                  inv_count: torch.Tensor | None = None) -> torch.Tensor:
    """``box_mean`` (the reference) for (..., H, W) with H, W >= 2r + 2, into ``out`` (may not be ``x``),
    using ``work`` (same shape) as scratch; ``inv_count`` from ``box_counts`` can be passed in."""
    if radius <= 0:
        return x if out is None else out.copy_(x)
    out = torch.empty_like(x) if out is None else out
    work = torch.empty_like(x) if work is None else work
    if radius <= SHIFTED_SUM_MAX_RADIUS:
        _shifted_sum_(x, radius, -1, work)
        _shifted_sum_(work, radius, -2, out)
    else:
        _box_sum_(x, radius, -1, out, work)
        _box_sum_(out, radius, -2, out, work)  # reads ``out`` only for the running sum, then overwrites it
    inv = box_counts(x.shape[-2], x.shape[-1], radius, x.device, x.dtype) if inv_count is None else inv_count
    return out.mul_(inv)
