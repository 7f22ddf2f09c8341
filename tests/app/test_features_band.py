"""The band path of SAM's mask upsampling (``mask_upsampling.stable_masks``: exact logits only near
the thresholds) against its twin, the dense path ``qr-cl features`` took before it (upsample every
mask the stability bound leaves, score, threshold at 0): the same masks, scores and positions, bit
for bit, on smooth, noisy and adversarial logits and on crops of many shapes."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from qr_cl.app.features import mask_upsampling
from qr_cl.app.features.mask_upsampling import ROUNDING_MARGIN, Taps, stability_bound, stable_masks, upsample
from qr_cl.app.features.sam_model import SAM_IMAGE_SIZE, upsampling_matrix

#: (height, width) of images or crops: the 640x480 frame, one of its four crops, small and odd
#: ones (a width that reads a few low-resolution columns, windows without outputs), and one larger
#: than SAM's input (up to 8 output rows per window).
SIZES = [(480, 640), (322, 402), (37, 61), (1000, 47), (1300, 1100)]


def _taps(height: int, width: int) -> tuple[Taps, Taps]:
    """The taps of an image of height x width, as ``SamImage`` makes them."""
    scale = SAM_IMAGE_SIZE / max(height, width)
    rh, rw = int(height * scale + 0.5), int(width * scale + 0.5)
    return Taps.of(upsampling_matrix(height, rh, 256)), Taps.of(upsampling_matrix(width, rw, 256))


def _dense(low, rows, cols, offset, stability):
    """The twin: every mask the bound leaves upsampled whole, scored (counts in int64, as before),
    thresholded at 0."""
    index = (stability_bound(low, rows, cols, offset) >= stability).nonzero()[:, 0]
    logits = upsample(low[index], rows, cols)
    scores = (logits > offset).flatten(1).sum(1) / (logits > -offset).flatten(1).sum(1)
    keep = scores >= stability
    return index[keep], logits[keep] > 0, scores[keep]


def _check(low, rows, cols, offset, stability, monkeypatch) -> int:
    """Assert the band path equals the twin bit for bit; returns the masks it upsampled whole."""
    dense = []
    with monkeypatch.context() as patch:
        patch.setattr(mask_upsampling, "upsample", lambda x, r, c: dense.append(len(x)) or upsample(x, r, c))
        index, masks, scores = stable_masks(low, rows, cols, offset, stability)
    ref_index, ref_masks, ref_scores = _dense(low, rows, cols, offset, stability)
    assert torch.equal(index, ref_index)
    assert masks.dtype == torch.bool and torch.equal(masks, ref_masks)
    assert scores.dtype == ref_scores.dtype and torch.equal(scores.view(torch.int32), ref_scores.view(torch.int32))
    return sum(dense)


def _blobs(n: int, h: int, w: int, gen: torch.Generator) -> torch.Tensor:
    """[n, h, w] cone-shaped logits (SAM-like smooth masks), shallow to steep."""
    yy, xx = torch.meshgrid(torch.arange(float(h)), torch.arange(float(w)), indexing="ij")
    centre = torch.rand(n, 2, 1, 1, generator=gen) * torch.tensor([h, w]).view(1, 2, 1, 1)
    radius = torch.rand(n, 1, 1, generator=gen) * min(h, w) / 3 + 2
    slope = torch.logspace(-1, 1.5, n)[:, None, None]
    return slope * (radius - ((yy - centre[:, 0]) ** 2 + (xx - centre[:, 1]) ** 2).sqrt())


def _near_thresholds(n: int, h: int, w: int, offset: float, gen: torch.Generator) -> torch.Tensor:
    """[n, h, w] logits in patches of a few entries, each patch one value at, one float from or at
    the rounding margin from -offset, 0 or +offset: uniform windows exactly at a threshold."""
    margin = ROUNDING_MARGIN * max(1.0, offset)
    values = []
    for t in (-offset, 0.0, offset):
        tt = torch.tensor(t)
        values += [t, t + margin, t - margin, torch.nextafter(tt, tt + 1).item(), torch.nextafter(tt, tt - 1).item()]
    values = torch.tensor(values + [offset * 3, -offset * 3])
    patches = torch.randint(len(values), (n, -(-h // 5), -(-w // 5)), generator=gen)
    return values[patches].repeat_interleave(5, 1).repeat_interleave(5, 2)[:, :h, :w].contiguous()


@pytest.mark.parametrize("size", SIZES)
@pytest.mark.parametrize("stability", [0.85, 0.0])
def test_smooth_masks_take_the_band_path(size, stability, monkeypatch):
    rows, cols = _taps(*size)
    gen = torch.Generator().manual_seed(size[0])
    low = _blobs(12, 256, 256, gen)
    assert _check(low, rows, cols, 1.0, stability, monkeypatch) == 0


@pytest.mark.parametrize("size", SIZES[:3])
def test_noisy_masks_are_upsampled_densely(size, monkeypatch):
    rows, cols = _taps(*size)
    gen = torch.Generator().manual_seed(1)
    low = _blobs(8, 256, 256, gen)
    low[::2] = torch.randn(4, 256, 256, generator=gen) * 3                   # every other one noise
    assert _check(low, rows, cols, 1.0, 0.0, monkeypatch) == 4


@pytest.mark.parametrize("size,offset", [(size, 1.0) for size in SIZES] + [(SIZES[1], 0.25), (SIZES[2], 4.0)])
def test_logits_at_the_thresholds(size, offset, monkeypatch):
    """Values at, next to and at the margin from every threshold, all through the band path."""
    rows, cols = _taps(*size)
    gen = torch.Generator().manual_seed(2)
    low = _near_thresholds(6, 256, 256, offset, gen)
    monkeypatch.setattr(mask_upsampling, "DENSE_BAND", 2.0)
    assert _check(low, rows, cols, offset, 0.0, monkeypatch) == 0
    noisy = torch.randn(2, 256, 256, generator=gen) * 2                     # noisy ones too, all band
    assert _check(noisy, rows, cols, offset, 0.0, monkeypatch) == 0


@pytest.mark.parametrize("size", SIZES[:4])
def test_empty_full_and_flat_masks(size, monkeypatch):
    rows, cols = _taps(*size)
    flat = torch.tensor([-5.0, -1.0, -0.5, 0.0, 0.5, 1.0, 5.0])[:, None, None].expand(7, 256, 256).contiguous()
    assert _check(flat, rows, cols, 1.0, 0.0, monkeypatch) == 1             # 0 everywhere: all band, dense
    index, masks, scores = stable_masks(flat, rows, cols, 1.0, 0.0)
    kept = {int(i): (m, float(s)) for i, m, s in zip(index, masks, scores)}
    assert 0 not in kept                                                    # nothing above -1: 0 / 0
    assert [kept[i][1] for i in (2, 3, 4, 6)] == [0, 0, 0, 1]
    assert not kept[2][0].any() and not kept[3][0].any() and kept[4][0].all() and kept[6][0].all()


def test_no_masks_and_none_passing(monkeypatch):
    rows, cols = _taps(480, 640)
    index, masks, scores = stable_masks(torch.zeros(0, 256, 256), rows, cols, 1.0, 0.85)
    assert index.shape == scores.shape == (0,) and masks.shape == (0, 480, 640)
    gen = torch.Generator().manual_seed(3)
    low = torch.cat([_blobs(3, 256, 256, gen), torch.randn(3, 256, 256, generator=gen)])
    _check(low, rows, cols, 1.0, 1.0, monkeypatch)
    assert len(stable_masks(low, rows, cols, 1.0, 1.0)[0]) == 0


def test_logits_that_are_not_finite(monkeypatch):
    """A window holding inf or nan goes dense (a zero weight times inf is nan there); a value no
    tap reads changes nothing."""
    rows, cols = _taps(480, 640)
    gen = torch.Generator().manual_seed(4)
    low = _blobs(5, 256, 256, gen)
    low[0, 40, 50], low[1, 100, 0], low[2, 7, 7] = float("inf"), -float("inf"), float("nan")
    low[3, 255, 255] = float("nan")                                         # rows past rows.reads are not read
    assert rows.reads + rows.span - 1 < 256
    assert _check(low, rows, cols, 1.0, 0.0, monkeypatch) == 3


def test_low_cut_to_what_the_upsampling_reads(monkeypatch):
    """SamImage.low_masks gives the grid only up to the taps' reads (rounded up to 4): the taps
    of the last rows and columns are clamped there, in both paths alike."""
    gen = torch.Generator().manual_seed(5)
    for size in SIZES:
        rows, cols = _taps(*size)
        h, w = -(-rows.reads // 4) * 4, -(-cols.reads // 4) * 4
        low = _blobs(4, h, w, gen)
        assert _check(low, rows, cols, 1.0, 0.0, monkeypatch) == 0


@pytest.mark.parametrize("size", SIZES)
def test_taps_meet_the_margins_premises(size):
    """The rounding margin assumes non-negative weights whose rows sum to 1 within 3 * 2^-24, and
    the band's blocks outputs whose first taps never decrease."""
    for taps in _taps(*size):
        assert (taps.weights >= 0).all()
        assert (taps.weights.double().sum(1) - 1).abs().max() <= 3 * 2.0 ** -24
        assert (taps.first[1:] >= taps.first[:-1]).all()
        assert np.isclose(float(taps.windows.sum()), len(taps.first))
