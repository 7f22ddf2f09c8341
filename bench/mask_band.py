"""Milliseconds per batch of SAM masks for their upsampling, stability score and threshold at 0:
the dense path (``stability_bound``, then ``upsample``, the stability score and ``> 0`` of the masks
it leaves, as ``qr-cl features`` did) against the band path (``mask_upsampling.stable_masks``),
both in this process on the same inputs, alternating, their outputs checked equal bit for bit.

The taps are those of a 640x480 frame's whole-image view. Inputs, a batch each:

- ``random SAM``: the low-resolution logits of the benchmarks' random-weight SAM ViT-B (seed 2, as
  bench/features_rate.py) for the first ``--batches`` batches of 64 point prompts on its image,
  after the IoU filter. Random weights make high-frequency logits: nearly every window straddles
  0, so these masks take the dense path;
- ``blobs``: 64 cone-shaped logits, smooth masks like a trained SAM's (slopes 0.3 to 10 per
  low-resolution entry);
- ``noise a``: 16 blobs plus Gaussian noise of amplitude a, all through the band (``DENSE_BAND``
  lifted): where the band stops paying, the break-even that sets ``DENSE_BAND``.

Per input: masks per batch, the fraction of their pixels in the band (windows straddling -1, 0 or
+1) and in the windows straddling 0, the median and minimum ms of each path over ``--repeats``
rounds after a warm-up, and the ratio dense / band of the medians::

    python bench/mask_band.py --batches 3 --repeats 5 --out bench/reports/mask-band-<machine>/report.md
"""
from __future__ import annotations

import argparse
import os
import platform
import statistics
from pathlib import Path

import numpy as np
import torch

from benchutil import print_table, timing
from features_rate import HEIGHT, WIDTH, test_image

BATCH = 64
NOISE = (1.0, 3.0, 10.0, 30.0)
#: LangSplat's stability filter (MaskSettings' defaults).
OFFSET, STABILITY = 1.0, 0.85


def random_sam_batches(batches: int, data: Path | None) -> tuple[list[torch.Tensor], object, object, str]:
    """([M, h, w] low-resolution logits per batch, after the IoU filter; the view's row and column
    taps; the image's description) of the random-weight SAM ViT-B on features_rate's 640x480 image."""
    from qr_cl.app.features.masks import MaskSettings, point_grid
    from qr_cl.app.features.random_models import SAM_ARCHITECTURES, random_sam

    sam, settings = random_sam(SAM_ARCHITECTURES["vit_b"], seed=2), MaskSettings()
    image, source = test_image(data)
    view = sam.embed(image)
    points = point_grid(settings.points_per_side) * np.array([WIDTH, HEIGHT])
    lows = []
    for start in range(0, batches * BATCH, BATCH):
        tokens, iou = view.decode(points[start:start + BATCH])
        passing = iou > settings.pred_iou
        prompts = passing.any(1)
        lows.append(view.low_masks(tokens.take(prompts)).flatten(0, 1)[passing[prompts].flatten()])
    return lows, view.rows, view.cols, source


def blobs(n: int, h: int, w: int, gen: torch.Generator, slopes: torch.Tensor) -> torch.Tensor:
    """[n, h, w] cone-shaped logits: discs of radius 5 to 65 entries, ``slopes`` [n] per entry."""
    yy, xx = torch.meshgrid(torch.arange(float(h)), torch.arange(float(w)), indexing="ij")
    centre = torch.rand(n, 2, 1, 1, generator=gen) * torch.tensor([h, w]).view(1, 2, 1, 1)
    radius = torch.rand(n, 1, 1, generator=gen) * 60 + 5
    return slopes[:, None, None] * (radius - ((yy - centre[:, 0]) ** 2 + (xx - centre[:, 1]) ** 2).sqrt())


def band_fractions(low: torch.Tensor, rows, cols) -> tuple[float, float]:
    """(mean fraction of the output pixels in the band, in the windows straddling 0) over the masks
    of ``low`` that pass the stability bound."""
    from qr_cl.app.features import mask_upsampling as mu

    keep = mu.stability_bound(low, rows, cols, OFFSET) >= STABILITY
    top, bottom = mu._window_extreme(low[keep], rows, cols, True), mu._window_extreme(low[keep], rows, cols, False)
    margin, size = mu._margin(OFFSET), len(rows.first) * len(cols.first)
    band = mu._straddling(top, bottom, (-OFFSET, 0.0, OFFSET), margin)
    zero = mu._straddling(top, bottom, (0.0,), margin)
    return float(mu._count(band, rows, cols).mean()) / size, float(mu._count(zero, rows, cols).mean()) / size


def dense_path(low: torch.Tensor, rows, cols):
    """What ``qr-cl features`` did: the bound, then every mask it leaves upsampled whole, its
    score counted in int64."""
    from qr_cl.app.features.mask_upsampling import stability_bound, upsample

    index = (stability_bound(low, rows, cols, OFFSET) >= STABILITY).nonzero()[:, 0]
    logits = upsample(low[index], rows, cols)
    scores = (logits > OFFSET).flatten(1).sum(1) / (logits > -OFFSET).flatten(1).sum(1)
    keep = scores >= STABILITY
    return index[keep], logits[keep] > 0, scores[keep]


def compare(low: torch.Tensor, rows, cols, repeats: int, dense_band: float | None = None) -> dict:
    """Both paths on ``low``, alternating, after one warm-up call each; ``dense_band`` replaces
    ``DENSE_BAND`` where given."""
    from qr_cl.app.features import mask_upsampling as mu

    saved = mu.DENSE_BAND
    mu.DENSE_BAND = saved if dense_band is None else dense_band
    try:
        times = {"dense": [], "band": []}
        for round_ in range(repeats + 1):
            ref, t_dense = timing.timed(lambda: dense_path(low, rows, cols))
            got, t_band = timing.timed(lambda: mu.stable_masks(low, rows, cols, OFFSET, STABILITY))
            if not (torch.equal(got[0], ref[0]) and torch.equal(got[1], ref[1])
                    and torch.equal(got[2].view(torch.int32), ref[2].view(torch.int32))):
                raise SystemExit("the band path's output differs from the dense path's")
            if round_:
                times["dense"].append(t_dense)
                times["band"].append(t_band)
    finally:
        mu.DENSE_BAND = saved
    band, zero = band_fractions(low, rows, cols)
    return {"masks": len(low), "kept": len(ref[0]), "band": band, "zero": zero,
            **{f"{k}_ms": 1e3 * statistics.median(v) for k, v in times.items()},
            **{f"{k}_min_ms": 1e3 * min(v) for k, v in times.items()}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--batches", type=int, default=3, help="batches of 64 prompts of the random SAM")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--out", type=Path, help="write the table to this Markdown file")
    args = parser.parse_args()
    from qr_cl.app.process import keep_freed_memory

    keep_freed_memory()                                                    # as qr-cl features does
    torch.set_num_threads(args.threads)
    lows, rows, cols, source = random_sam_batches(args.batches, args.data)
    gen = torch.Generator().manual_seed(0)
    h, w = lows[0].shape[1:]
    rows_out = [(f"random SAM, batch {i + 1}", compare(low, rows, cols, args.repeats)) for i, low in enumerate(lows)]
    rows_out.append(("blobs", compare(blobs(BATCH, h, w, gen, torch.logspace(-0.5, 1, BATCH)), rows, cols, args.repeats)))
    base = blobs(16, h, w, gen, torch.ones(16))
    for amplitude in NOISE:
        low = base + amplitude * torch.randn(base.shape, generator=gen)
        rows_out.append((f"noise {amplitude:g}, all band", compare(low, rows, cols, args.repeats, float("inf"))))
    lines = [f"# Mask upsampling: dense path against band path ({WIDTH}x{HEIGHT} view, {args.threads} torch threads)", "",
             f"Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, torch {torch.__version__}; "
             f"image: {source}; load average before the table {os.getloadavg()[0]:.2f}. Made by bench/mask_band.py; median (min) ms "
             f"of {args.repeats} rounds; outputs equal bit for bit.", "",
             "| input | masks (kept) | band | straddling 0 | dense path ms | band path ms | dense / band |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for name, r in rows_out:
        lines.append(f"| {name} | {r['masks']} ({r['kept']}) | {r['band']:.3f} | {r['zero']:.3f} | "
                     f"{r['dense_ms']:.0f} ({r['dense_min_ms']:.0f}) | {r['band_ms']:.0f} ({r['band_min_ms']:.0f}) | "
                     f"{r['dense_ms'] / r['band_ms']:.2f} |")
    print_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
