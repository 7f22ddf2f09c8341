"""SAM's mask logits from its [256, 256] grid to the image's size, and a bound on their stability
score that needs no upsampling.

SAM upsamples the low-resolution logits bilinearly to 1024, crops the resized image and resizes
that to the image's size (:func:`~.sam_model.upsampling_matrix`, one linear map per axis). Each
output row (column) reads at most a few consecutive low-resolution rows (columns), its taps:
:class:`Taps` holds them, and :func:`upsample` applies them, the same numbers as the dense maps.

Every output logit is a convex combination of its taps (non-negative weights summing to one), so
it is above a threshold only where the largest of its taps is, and above it wherever the smallest
is. Counting, over the output pixels, the windows of taps whose maximum (minimum) passes gives an
upper (lower) bound of the pixels that pass, from a max (min) pool of the low-resolution grid and
the number of output rows and columns that read each window: :func:`stability_bound` is an upper
bound of the stability score (:func:`~.masks.stability_scores`), a filter that drops no mask the
exact score keeps.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

#: Margin on the thresholds of :func:`stability_bound` for the rounding of the upsampling's sums.
ROUNDING_MARGIN = 1e-3


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
    gathered at a time)."""
    out = None
    for k in range(taps.span):
        term = x.index_select(1, (taps.first + k).clamp(max=x.shape[1] - 1)) * taps.weights[:, k, None]
        out = term if out is None else out.add_(term)
    return out


def upsample(low: torch.Tensor, rows: Taps, cols: Taps) -> torch.Tensor:
    """[..., H, W] logits at the image's size from SAM's ``low`` [..., h, w] (h, w at least the
    taps' reads): the columns, then the rows."""
    flat = low.flatten(0, -3) if low.dim() > 2 else low[None]
    wide = _resize(flat.transpose(1, 2), cols).transpose(1, 2).contiguous()          # [M, h, W]
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


def stability_bound(low: torch.Tensor, rows: Taps, cols: Taps, offset: float) -> torch.Tensor:
    """[M] upper bound of the stability score (pixels above +``offset`` over pixels above
    -``offset``, at most 1) of the upsampled logits of ``low`` [M, h, w] (module docstring); 1
    where no window is certainly above -``offset``."""
    above = _count(_window_extreme(low, rows, cols, True) > offset - ROUNDING_MARGIN, rows, cols)
    floor = _count(_window_extreme(low, rows, cols, False) > -offset + ROUNDING_MARGIN, rows, cols)
    return torch.where(floor > 0, (above / floor.clamp_min(1)).clamp_max(1), torch.ones_like(above))
