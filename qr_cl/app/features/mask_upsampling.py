"""SAM's mask logits from its [256, 256] grid to the image's size, a bound on their stability
score that needs no upsampling, and the masks and exact scores with only their band upsampled.

SAM upsamples the low-resolution logits bilinearly to 1024, crops the resized image and resizes
that to the image's size (:func:`~.sam_model.upsampling_matrix`, one linear map per axis). Each
output row (column) reads at most a few consecutive low-resolution rows (columns), its taps:
:class:`Taps` holds them, and :func:`upsample` applies them, the same numbers as the dense maps.

Every output logit is a convex combination of its taps (non-negative weights summing to one), so
it is above a threshold only where the largest of its taps is, and above it wherever the smallest
is. Counting, over the output pixels, the windows of taps whose maximum (minimum) passes gives an
upper (lower) bound of the pixels that pass, from a max (min) pool of the low-resolution grid and
the number of output rows and columns that read each window: :func:`stability_bound` is an upper
bound of the stability score (:func:`stability_scores`), a filter that drops no mask the exact
score keeps.

The same windows decide most pixels outright: a pixel whose window's minimum is above a threshold
by the rounding margin is above it, one whose maximum is below it by the margin is not. Only the
band, the windows that straddle -offset, 0 or +offset within the margin, needs its logits:
:func:`stable_masks` computes them with :func:`upsample`'s products summed in its order (the same
float32 values), counts the other pixels per window, and so gives the masks (logits above 0) and
scores of the dense path bit for bit. Masks whose logits are noisy (many windows straddle 0,
:data:`DENSE_BAND`) or not all finite (inf times a zero weight is nan) are upsampled densely, a
few at a time (:data:`DENSE_CHUNK`).

The rounding margin. The weights are the dense maps' float64 entries rounded to float32:
non-negative, each row summing to 1 within 3u (u = 2^-24), so a pixel's weights w (both axes) sum
to s with |s - 1| <= 6u, and the exact sum S = sum(w x) of its taps x lies between s min(x) and
s max(x). :func:`upsample` rounds three products and two additions per axis, so its logit is
within about 6u sum(w|x|) of S. Where every tap is above t + d (d > 0), |x| <= x + 2|t|, so
sum(w|x|) <= S + 2|t|s and the logit is above t once d > 30u|t| (any d for t = 0); mirrored, taps
all below t - d give a logit below t. The margin, :data:`ROUNDING_MARGIN` times max(1, offset),
is over 500 times 30u|t| at each threshold, room enough for the thresholds' own float32 rounding.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

#: Margin on thresholds up to 1 for the rounding of the upsampling's sums, scaled by larger ones
#: (module docstring).
ROUNDING_MARGIN = 1e-3
#: A mask whose windows straddling 0 hold more than this fraction of its pixels (noisy logits) is
#: upsampled densely: about where the band's logits, each costing several dense ones, cost as much
#: as the dense upsampling (bench/mask_band.py).
DENSE_BAND = 0.1
#: Masks upsampled densely at a time (their logits, 1.2 MB each at 640x480, stay in cache
#: from the upsampling through the score and the threshold).
DENSE_CHUNK = 4


@dataclass(frozen=True)
class Taps:
    """One axis of a linear resize: output i = sum_k ``weights``[i, k] * input[``first``[i] + k];
    ``reads`` input entries are read in all (the rest may be left out), ``windows`` [reads] counts
    the outputs whose taps start at each input."""

    first: torch.Tensor
    weights: torch.Tensor
    reads: int
    windows: torch.Tensor

    @staticmethod
    def of(matrix: torch.Tensor) -> "Taps":
        """The taps of a dense [out, in] resize ``matrix`` (non-negative, rows summing to one)."""
        nonzero = matrix != 0
        first = nonzero.to(torch.int8).argmax(1)
        last = matrix.shape[1] - 1 - nonzero.flip(1).to(torch.int8).argmax(1)
        span = int((last - first).max()) + 1
        index = first[:, None] + torch.arange(span)
        weights = torch.where(index <= last[:, None], matrix.gather(1, index.clamp(max=matrix.shape[1] - 1)), 0)
        reads = int(last.max()) + 1
        return Taps(first, weights, reads, torch.bincount(first, minlength=reads).to(matrix.dtype))

    @property
    def span(self) -> int:
        """Taps per output."""
        return self.weights.shape[1]

    def to(self, device) -> "Taps":
        return Taps(self.first.to(device), self.weights.to(device), self.reads, self.windows.to(device))


def _resize(x: torch.Tensor, taps: Taps) -> torch.Tensor:
    """[M, out, k] of ``x`` [M, n, k] resized along its middle axis by ``taps`` (whole rows of k
    gathered at a time, each tap's products into one reused buffer, added in the taps' order)."""
    last = x.shape[1] - 1
    out = torch.index_select(x, 1, taps.first.clamp(max=last)).mul_(taps.weights[:, 0, None])
    term = torch.empty_like(out)
    for k in range(1, taps.span):
        torch.index_select(x, 1, (taps.first + k).clamp(max=last), out=term)
        out.add_(term.mul_(taps.weights[:, k, None]))
    return out


def upsample(low: torch.Tensor, rows: Taps, cols: Taps) -> torch.Tensor:
    """[..., H, W] logits at the image's size from SAM's ``low`` [..., h, w] (h, w at least the
    taps' reads): the columns, then the rows."""
    flat = low.flatten(0, -3) if low.dim() > 2 else low[None]
    wide = _resize(flat.transpose(1, 2).contiguous(), cols).transpose(1, 2).contiguous()   # [M, h, W]
    return _resize(wide, rows).view(*low.shape[:-2], len(rows.first), len(cols.first))


def _window_extreme(low: torch.Tensor, rows: Taps, cols: Taps, largest: bool) -> torch.Tensor:
    """[M, rows.reads, cols.reads]: the max (``largest``) or min of ``low`` [M, h, w] over each
    window of rows.span x cols.span entries that starts there (cut at the grid's end)."""
    pick = torch.maximum if largest else torch.minimum
    x = low[:, :rows.reads + rows.span - 1, :cols.reads + cols.span - 1]
    rows_out = x[:, :rows.reads]
    for k in range(1, rows.span):
        rows_out = pick(rows_out, x[:, k:k + rows.reads].expand_as(rows_out) if x.shape[1] >= k + rows.reads
                        else torch.cat([x[:, k:], x[:, -1:].expand(-1, k + rows.reads - x.shape[1], -1)], 1))
    out = rows_out[..., :cols.reads]
    for k in range(1, cols.span):
        shifted = rows_out[..., k:k + cols.reads]
        if shifted.shape[-1] < cols.reads:
            shifted = torch.cat([shifted, rows_out[..., -1:].expand(-1, -1, cols.reads - shifted.shape[-1])], -1)
        out = pick(out, shifted)
    return out


def _count(passing: torch.Tensor, rows: Taps, cols: Taps) -> torch.Tensor:
    """[M] output pixels whose window passes, of ``passing`` [M, rows.reads, cols.reads] bool."""
    return (rows.windows @ passing.to(rows.windows.dtype)) @ cols.windows


def _exact_count(passing: torch.Tensor, rows: Taps, cols: Taps) -> torch.Tensor:
    """[M] int64 output pixels whose window passes, of ``passing`` [M, rows.reads, cols.reads]
    bool (float32 sums of whole numbers up to the width, so exact; then integers)."""
    per_row = (passing.to(cols.windows.dtype) @ cols.windows).long()
    return (per_row * rows.windows.long()).sum(1)


def _margin(offset: float) -> float:
    """The rounding margin at thresholds up to ``offset`` in size (module docstring)."""
    return ROUNDING_MARGIN * max(1.0, abs(offset))


def _bound(top: torch.Tensor, bottom: torch.Tensor, rows: Taps, cols: Taps, offset: float) -> torch.Tensor:
    """:func:`stability_bound` from the windows' maxima ``top`` and minima ``bottom`` [M, R, C]."""
    margin = _margin(offset)
    above = _count(top > offset - margin, rows, cols)
    floor = _count(bottom > -offset + margin, rows, cols)
    return torch.where(floor > 0, (above / floor.clamp_min(1)).clamp_max(1), torch.ones_like(above))


def stability_bound(low: torch.Tensor, rows: Taps, cols: Taps, offset: float) -> torch.Tensor:
    """[M] upper bound of the stability score (pixels above +``offset`` over pixels above
    -``offset``, at most 1) of the upsampled logits of ``low`` [M, h, w] (module docstring); 1
    where no window is certainly above -``offset``."""
    return _bound(_window_extreme(low, rows, cols, True), _window_extreme(low, rows, cols, False), rows, cols, offset)


def stability_scores(logits: torch.Tensor, offset: float) -> torch.Tensor:
    """[n] pixels above +offset over pixels above -offset of ``logits`` [n, H, W] (counted as bytes
    in int32, faster than bools or int64, the same float32 quotient)."""
    flat = logits.flatten(1)
    above, floor = ((flat > t).view(torch.uint8).sum(1, dtype=torch.int32) for t in (offset, -offset))
    return above / floor


def _blocks(taps: Taps) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(start, count [reads] int64, weights [K, span, reads]): the outputs whose taps start at
    input r are start[r] + k for k < count[r] (``first`` never decreases along the outputs), with
    the weights weights[k, :, r]; K is the most outputs of one input (padding beyond count[r])."""
    inputs = torch.arange(taps.reads, device=taps.first.device)
    start = torch.searchsorted(taps.first, inputs)
    count = torch.searchsorted(taps.first, inputs, right=True) - start
    outputs = (start[:, None] + torch.arange(int(count.max()), device=start.device)).clamp(max=len(taps.first) - 1)
    return start, count, taps.weights[outputs].permute(1, 2, 0).contiguous()


def _weighted_sum(terms: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """The sum of x * w over ``terms`` (x, w), the products added one by one in order, as
    :func:`_resize` adds its terms."""
    out = None
    for x, w in terms:
        out = x * w if out is None else out + x * w
    return out


@dataclass
class _Band:
    """The band's B windows, each with its block of output pixels, padded to the most outputs of
    one window per axis (Kr x Kc; B last, for contiguous arithmetic): ``mask`` [B] the mask of each
    window, ``corner`` [B] its block's first pixel (row * W + column), ``logits`` [Kr, Kc, B] as
    :func:`upsample` computes them, ``inside`` [Kr, Kc, B] bool the block's real pixels."""

    mask: torch.Tensor
    corner: torch.Tensor
    logits: torch.Tensor
    inside: torch.Tensor

    def counts(self, threshold: float, masks: int) -> torch.Tensor:
        """[``masks``] int64: the band's pixels of each mask whose logit is above ``threshold``."""
        per_window = ((self.logits > threshold) & self.inside).sum((0, 1))
        return torch.zeros(masks, dtype=per_window.dtype, device=per_window.device).index_add_(0, self.mask, per_window)


def _band_logits(low: torch.Tensor, rows: Taps, cols: Taps, band: torch.Tensor) -> _Band:
    """The output pixels of the windows ``band`` [M, R, C] bool of ``low`` [M, h, w], each with
    its logit as :func:`upsample` computes it: the same products summed in the same order, columns
    then rows, a window's taps gathered once and its columns' sums shared by its rows."""
    mask, r, c = band.nonzero(as_tuple=True)
    h, w = low.shape[1:]
    row_taps = (r + torch.arange(rows.span, device=r.device)[:, None]).clamp(max=h - 1)   # [rows.span, B]
    col_taps = (c + torch.arange(cols.span, device=c.device)[:, None]).clamp(max=w - 1)
    flat = ((mask * h + row_taps) * w)[:, None] + col_taps[None]
    taps = low.reshape(-1).index_select(0, flat.flatten()).view(flat.shape)             # [rows.span, cols.span, B]
    row_start, row_count, row_weights = _blocks(rows)
    col_start, col_count, col_weights = _blocks(cols)
    col_weights = col_weights.flatten(0, 1).index_select(1, c).view(*col_weights.shape[:2], -1)   # [Kc, cols.span, B]
    row_weights = row_weights.flatten(0, 1).index_select(1, r).view(*row_weights.shape[:2], -1)   # [Kr, rows.span, B]
    wide = _weighted_sum([(taps[:, k, None], col_weights[None, :, k]) for k in range(cols.span)])  # [rows.span, Kc, B]
    logits = _weighted_sum([(wide[None, k], row_weights[:, k, None]) for k in range(rows.span)])   # [Kr, Kc, B]
    kr, kc = logits.shape[:2]
    inside = ((torch.arange(kr, device=r.device)[:, None] < row_count[r])[:, None]
              & (torch.arange(kc, device=c.device)[:, None] < col_count[c])[None])
    return _Band(mask, row_start[r] * len(cols.first) + col_start[c], logits, inside)


def _straddling(top: torch.Tensor, bottom: torch.Tensor, thresholds: tuple[float, ...], margin: float) -> torch.Tensor:
    """[M, R, C] bool: windows (maxima ``top``, minima ``bottom`` [M, R, C]) that straddle one of
    the ``thresholds`` within ``margin``: neither certainly above it nor certainly below."""
    out = None
    for t in thresholds:
        near = (bottom <= t + margin) & (top >= t - margin)
        out = near if out is None else out.logical_or_(near)
    return out


def _painted(above: torch.Tensor, band: _Band, kept: torch.Tensor, rows: Taps, cols: Taps) -> torch.Tensor:
    """[n, H, W] bool: the ``kept`` [M] bool masks, each pixel from its window's ``above`` [M, R, C]
    bool, the pixels of ``band`` from their logits."""
    n, height, width = int(kept.sum()), len(rows.first), len(cols.first)
    out = torch.empty(n * height * width + 1, dtype=torch.bool, device=above.device)   # the last: where padding goes
    masks = out[:-1].view(n, height, width)
    columns = above[kept]
    columns = torch.gather(columns, 2, cols.first.expand(n, columns.shape[1], width))    # faster than index_select
    torch.index_select(columns, 1, rows.first, out=masks)                                # whole rows
    kr, kc = band.logits.shape[:2]
    offsets = (torch.arange(kr, device=out.device)[:, None] * width + torch.arange(kc, device=out.device))[:, :, None]
    pixel = ((kept.cumsum(0) - 1) * (height * width)).index_select(0, band.mask) + band.corner + offsets
    out[torch.where(band.inside & kept.index_select(0, band.mask), pixel, len(out) - 1)] = band.logits > 0
    return masks


def _dense_scores_and_masks(low: torch.Tensor, rows: Taps, cols: Taps, offset: float,
                            stability: float) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """(scores [M], masks of those scoring at least ``stability``: [n_i, H, W] bool per chunk) of
    ``low`` [M, h, w] upsampled densely, :data:`DENSE_CHUNK` masks at a time."""
    scores, masks = [], []
    for start in range(0, len(low), DENSE_CHUNK):
        logits = upsample(low[start:start + DENSE_CHUNK], rows, cols)
        scores.append(stability_scores(logits, offset))
        masks.append((logits > 0)[scores[-1] >= stability])                   # bools, not logits, picked
    return (torch.cat(scores) if scores else low.new_empty(0)), masks


def stable_masks(low: torch.Tensor, rows: Taps, cols: Taps, offset: float,
                 stability: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(index [n] int64, masks [n, H, W] bool, scores [n] float32) of the masks of ``low`` [M, h, w]
    whose upsampled logits have a stability score (:func:`stability_scores` at ``offset``) of at
    least ``stability``: their positions in ``low``, their logits above 0, their scores. Bit for
    bit the dense path's (:func:`upsample`, the score, the threshold), with only the masks that
    pass :func:`stability_bound` scored and only their band upsampled (module docstring); masks
    with a logit that is not finite or with many windows straddling 0 (:data:`DENSE_BAND`) are
    upsampled densely."""
    top, bottom = _window_extreme(low, rows, cols, True), _window_extreme(low, rows, cols, False)
    index = (_bound(top, bottom, rows, cols, offset) >= stability).nonzero()[:, 0]
    margin, size = _margin(offset), len(rows.first) * len(cols.first)
    zero = _straddling(top, bottom, (0.0,), margin)
    finite = (top.flatten(1).amax(1) < math.inf) & (bottom.flatten(1).amin(1) > -math.inf)
    dense = (~finite | (_count(zero, rows, cols) > DENSE_BAND * size))[index]
    scores = torch.empty(len(index), device=low.device)
    dense_scores, dense_masks = _dense_scores_and_masks(low[index[dense]], rows, cols, offset, stability)
    scores[dense] = dense_scores
    sparse = index[~dense]
    bottom = bottom[sparse]
    band = zero[sparse] | _straddling(top[sparse], bottom, (-offset, offset), margin)
    exact = _band_logits(low[sparse], rows, cols, band)
    passes = _exact_count(bottom > offset + margin, rows, cols) + exact.counts(offset, len(band))
    floor = _exact_count((bottom > margin - offset) & ~band, rows, cols) + exact.counts(-offset, len(band))
    scores[~dense] = passes / floor
    keep = scores >= stability
    masks = torch.empty(int(keep.sum()), len(rows.first), len(cols.first), dtype=torch.bool, device=low.device)
    rank = keep.cumsum(0) - 1
    at = rank[keep & dense]
    for part in dense_masks:                                                         # each chunk's, in order
        masks[at[:len(part)]] = part
        at = at[len(part):]
    masks[rank[keep & ~dense]] = _painted(bottom > margin, exact, keep[~dense], rows, cols)
    return index[keep], masks, scores[keep]
