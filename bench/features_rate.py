"""Frames per second of ``qr-cl features`` on this machine's CPU at 640x480 with LangSplat's
settings (4 levels from SAM's 32x32 point grid on the image and 2x2 crops, CLIP per mask), for
the real architectures with seeded random weights (SAM ViT-H/L/B, CLIP ViT-B/16).

A whole frame takes many minutes on 2 cores, and how many masks it has depends on the weights
(random ones give arbitrary masks), so the frame time is composed from timed parts, each the
median of ``--rounds`` runs on a 640x480 image (a rendered fox view when ``--data`` has the fox):

- one SAM image embedding (1024x1024 input), made once per crop: 5 per frame;
- one decoder batch of 64 point prompts with its masks' filtering (stability, boxes, crop
  edge) at the crop's size: 16 batches per crop, 80 per frame;
- CLIP's image encoder per mask crop (``--batch`` crops at a time), times the number of masks
  (``--masks``; LangSplat's four levels together typically hold one to a few hundred).
NMS, small-region removal, LangSplat's overlap filter and cropping are left out of the sum.

``--end-to-end`` also runs ``frame_features`` once with a lighter grid (``--points-per-side``,
no crops) and compares it with the parts' sum for the same settings, as a check of the model.
Writes ``report.md`` and ``results.json`` into ``--out``.
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from qr_cl.app.features.frames import encode_crops, frame_features
from qr_cl.app.features.masks import MaskSettings, crop_boxes, point_grid, stability_scores
from qr_cl.app.features.random_models import CLIP_ARCHITECTURES, SAM_ARCHITECTURES, random_clip, random_sam

WIDTH, HEIGHT = 640, 480


def _median_seconds(fn, rounds: int) -> float:
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def test_image(data: Path | None) -> tuple[np.ndarray, str]:
    """A 640x480 RGB image: a rendered fox view when the data has the fox, else a drawn one."""
    fox = data / "wakufactory-fox" / "fox.ply" if data else None
    if fox is not None and fox.is_file():
        from qr_cl.app.cli import render_views
        from qr_cl.scene import load_ply, orbit_cameras
        import tempfile
        g = load_ply(fox)
        out = Path(tempfile.mkdtemp())
        render_views(g, orbit_cameras(g.means, 1, WIDTH, HEIGHT, up_axis=1), out, None)
        return np.asarray(Image.open(out / "000_rgb.png").convert("RGB")), "a rendered fox view"
    yy, xx = np.mgrid[:HEIGHT, :WIDTH]
    img = np.stack([xx % 256, yy % 256, (xx + yy) % 256], -1).astype(np.uint8)
    return img, "a drawn gradient"


def decoder_batch(view, settings: MaskSettings, size: tuple[int, int]) -> None:
    """One batch of point prompts through the decoder and the per-mask filters."""
    points = point_grid(settings.points_per_side)[:settings.points_per_batch] * np.array(size[::-1])
    logits, iou = view.predict(points)
    logits = logits.flatten(0, 1)
    stab = stability_scores(logits, settings.stability_offset)
    (logits > 0).any(), stab.sum()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sam", nargs="+", default=["vit_h", "vit_b"], choices=sorted(SAM_ARCHITECTURES))
    parser.add_argument("--clip", default="ViT-B-16", choices=sorted(CLIP_ARCHITECTURES))
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--masks", type=int, nargs="+", default=[100, 200, 300])
    parser.add_argument("--batch", type=int, default=32)
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--end-to-end", action="store_true")
    parser.add_argument("--points-per-side", type=int, default=4)
    parser.add_argument("--out", type=Path, default=Path("bench/reports/features-rate"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    image, source = test_image(args.data)
    settings = MaskSettings()
    crops = crop_boxes(HEIGHT, WIDTH, settings.crop_layers, settings.crop_overlap)
    batches = [-(-settings.points_per_side ** 2 // settings.points_per_batch)] * len(crops)
    clip = random_clip(CLIP_ARCHITECTURES[args.clip], seed=1)
    n = args.batch
    crops_in = torch.rand(n, 3, clip.arch.image_size, clip.arch.image_size)
    clip_s = _median_seconds(lambda: encode_crops(clip, crops_in, n), args.rounds) / n
    results = {"threads": args.threads, "image": source, "size": [WIDTH, HEIGHT], "clip": args.clip,
               "clip_seconds_per_mask": clip_s, "sam": {}, "machine": platform.processor() or platform.machine(),
               "torch": torch.__version__}
    for name in args.sam:
        sam = random_sam(SAM_ARCHITECTURES[name], seed=2)
        embeds = {}
        embed_s = _median_seconds(lambda: embeds.update(v=sam.embed(image)), args.rounds)
        batch_s = _median_seconds(lambda: decoder_batch(embeds["v"], settings, (HEIGHT, WIDTH)), args.rounds)
        sam_frame = len(crops) * embed_s + sum(batches) * batch_s
        entry = {"embed_seconds": embed_s, "decoder_batch_seconds": batch_s, "embeddings_per_frame": len(crops),
                 "decoder_batches_per_frame": sum(batches), "sam_seconds_per_frame": sam_frame}
        if args.end_to_end:
            light = MaskSettings(points_per_side=args.points_per_side, crop_layers=0)
            start = time.perf_counter()
            result = frame_features(sam, clip, image, light, args.batch)
            measured = time.perf_counter() - start
            light_batch_s = _median_seconds(lambda: decoder_batch(embeds["v"], light, (HEIGHT, WIDTH)), args.rounds)
            entry["end_to_end"] = {"points_per_side": args.points_per_side, "crop_layers": 0,
                                   "masks": sum(result.counts), "seconds": measured,
                                   "parts_seconds": embed_s + light_batch_s + sum(result.counts) * clip_s}
        entry["frames_per_second"] = {str(m): 1 / (sam_frame + m * clip_s) for m in args.masks}
        results["sam"][name] = entry
        del sam, embeds
    write_report(args.out, results, args.masks)


def write_report(out: Path, results: dict, masks: list[int]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    lines = [f"# qr-cl features: frames per second ({results['threads']} torch threads, CPU)", "",
             f"640x480, LangSplat's settings (32x32 points, 1+4 crops, 4 levels); CLIP {results['clip']} "
             f"{results['clip_seconds_per_mask']:.3f} s per mask crop; image: {results['image']}; torch "
             f"{results['torch']}. Random weights of the real architectures; frame time = embeddings x embed + "
             "decoder batches x batch + masks x CLIP (bench/features_rate.py).", "",
             "| SAM | embed (s) | decoder batch of 64 points (s) | SAM per frame (s) | "
             + " | ".join(f"frames/s at {m} masks" for m in masks) + " |",
             "| --- | --- | --- | --- | " + " | ".join("---" for _ in masks) + " |"]
    for name, e in results["sam"].items():
        lines.append(f"| {name} | {e['embed_seconds']:.1f} | {e['decoder_batch_seconds']:.2f} | "
                     f"{e['sam_seconds_per_frame']:.0f} | "
                     + " | ".join(f"{e['frames_per_second'][str(m)]:.5f} ({1 / e['frames_per_second'][str(m)] / 60:.1f} min/frame)"
                                  for m in masks) + " |")
    for name, e in results["sam"].items():
        if "end_to_end" in e:
            c = e["end_to_end"]
            lines += ["", f"Check ({name}): one whole frame at {c['points_per_side']}x{c['points_per_side']} points, no "
                      f"crops: {c['seconds']:.1f} s measured ({c['masks']} masks) against {c['parts_seconds']:.1f} s "
                      "from the parts."]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
