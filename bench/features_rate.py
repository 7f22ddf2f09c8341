"""Seconds per frame of ``qr-cl features`` on this machine's CPU at 640x480, per stage, for this
checkout and the release before it (``--base``, bench/ab.py), in one run.

Every case runs whole frames in fresh processes, each install as its ``qr-cl features`` sets the
process up (threads, and whether freed memory is kept). The models are the real architectures
with seeded random weights, saved once as their publishers' files and loaded by each install's
own loader: SAM ViT-B and ViT-H, MobileSAM's TinyViT, CLIP ViT-B/16. Random weights make
arbitrary masks: the number of masks per frame is reported with each case, and how many the
filters drop is not what real weights would drop. Cases:

- ``vit_b``, ``vit_h``: LangSplat's settings (32x32 points, 1 + 4 crops, 4 levels, CLIP on
  every mask), ``--threads`` torch threads, both installs (``vit_h`` of the base only with
  ``--base-vit-h``: it takes the longest);
- ``fast``: MobileSAM with ``--crop-layers 0`` (this checkout only; the base cannot load it);
- ``clip``: CLIP's image encoder alone, seconds per mask crop (random weights make few masks, a
  real frame has one to a few hundred distinct ones);
- ``workers``: ``qr-cl features`` itself on a scene of ``--frames`` copies of the image with the
  fast profile, ``--workers 1`` (all threads) against ``--workers 2``.

Per stage (this checkout): the SAM image encoder, the mask decoder, the upsampling and mask
filters, NMS and small-region cleanup, CLIP, and the rest; the base's decoder and upsampling are
one stage (its ``predict``). The outputs of the two installs' ``vit_b`` frames are compared (equal
mask ids per level, cosine of the feature rows). The machine's load (1-minute load average)
is read before and after each run. Writes ``report.md`` and ``results.json`` into ``--out``::

    git worktree add ../qr-cl-base <release before>
    python bench/features_rate.py --base ../qr-cl-base --out bench/reports/features-rate-<machine>
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from ab import THIS, Install, add_base_option, installs

WIDTH, HEIGHT = 640, 480
#: The stages timed in a worker: (label, module, attribute) of the functions wrapped, by install.
STAGES = [("SAM image encoder", "sam_model", "Sam.embed"),
          ("mask decoder", "sam_model", "SamImage.decode"),
          ("mask decoder", "sam_model", "SamImage.low_masks"),
          ("decoder and upsampling (base)", "sam_model", "SamImage.predict"),
          ("upsampling and mask filters", "sam_model", "SamImage.upsample"),
          ("upsampling and mask filters", "masks", "stability_bound"),
          ("upsampling and mask filters", "masks", "stability_scores"),
          ("upsampling and mask filters", "masks", "stable_masks"),
          ("NMS and cleanup", "masks", "nms"),
          ("NMS and cleanup", "masks", "_clean"),
          ("CLIP", "frames", "encode_crops")]


def load_average() -> float:
    return os.getloadavg()[0]


def _wrap_stages(totals: dict[str, float]) -> None:
    """Time the functions of :data:`STAGES` that this install has, adding into ``totals``; a
    stage called from inside another timed one is counted once (the outer)."""
    import importlib

    depth = [0]
    for label, module_name, attr in STAGES:
        module = importlib.import_module(f"qr_cl.app.features.{module_name}")
        owner, name = (getattr(module, attr.split(".")[0]), attr.split(".")[1]) if "." in attr else (module, attr)
        if not hasattr(owner, name) or (label.endswith("(base)") and hasattr(module, "PointDecoder")):
            continue

        def timed(*a, _fn=getattr(owner, name), _label=label, **k):
            start = time.perf_counter()
            depth[0] += 1
            try:
                return _fn(*a, **k)
            finally:
                depth[0] -= 1
                if depth[0] == 0:
                    totals[_label] = totals.get(_label, 0.0) + time.perf_counter() - start
        setattr(owner, name, timed)


def measure_clip(config: dict) -> dict:
    """Seconds per mask crop of CLIP's image encoder, ``config['crops']`` crops 32 at a time (the
    command's default batch), the median of 3 runs after a warm-up."""
    import statistics

    import torch

    from qr_cl.app.features.clip_model import load_clip
    from qr_cl.app.features.frames import encode_crops

    torch.set_num_threads(config["threads"])
    clip = load_clip(config["clip"])
    crops = torch.rand(config["crops"], 3, clip.arch.image_size, clip.arch.image_size,
                       generator=torch.Generator().manual_seed(0))
    encode_crops(clip, crops[:32], 32)
    times = []
    for _ in range(3):
        start = time.perf_counter()
        encode_crops(clip, crops, 32)
        times.append(time.perf_counter() - start)
    return {"seconds_per_crop": statistics.median(times) / len(crops), "crops": len(crops)}


def measure_frame(config: dict) -> dict:
    """One frame of ``config`` in this process's install: seconds, stages, mask counts; the
    outputs saved to ``config['save']``."""
    if config.get("case") == "clip":
        return measure_clip(config)
    import torch

    from qr_cl.app.features import command, frames
    from qr_cl.app.features.clip_model import load_clip
    from qr_cl.app.features.masks import MaskSettings
    from qr_cl.app.features.sam_model import load_sam

    torch.set_num_threads(config["threads"])
    if "keep_freed_memory()" in Path(command.__file__).read_text():     # as this install's command does
        from qr_cl.app.process import keep_freed_memory
        keep_freed_memory()
    clip, sam = load_clip(config["clip"]), load_sam(config["sam"])
    image = np.load(config["image"])
    totals: dict[str, float] = {}
    _wrap_stages(totals)
    load_before = load_average()
    start = time.perf_counter()
    result = frames.frame_features(sam, clip, image, MaskSettings(crop_layers=config["crop_layers"]))
    seconds = time.perf_counter() - start
    np.savez(config["save"], ids=result.ids, features=result.features)
    totals["rest (LangSplat filter, crops, id maps)"] = seconds - sum(totals.values())
    return {"seconds": seconds, "stages": totals, "counts": result.counts, "load": [load_before, load_average()],
            "torch": torch.__version__}


def run_frame(install: Install, config: dict, cwd: str) -> dict:
    proc = install.run([str(Path(__file__).resolve()), "--worker", json.dumps(config)], capture_output=True,
                       text=True, cwd=cwd)
    if proc.returncode:
        sys.exit(f"{install.label} frame failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def run_workers(models: dict, image: np.ndarray, frames: int, workers: int, threads: int, folder: Path) -> dict:
    """``qr-cl features`` (this checkout) on ``frames`` copies of the image with the fast profile."""
    from PIL import Image

    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from qr_cl.scene import Camera
    from tests.app.features_helpers import write_cameras

    scene, photos = folder / f"scene-{workers}", folder / f"photos-{workers}"
    scene.mkdir(parents=True)
    photos.mkdir()
    cams = []
    for i in range(frames):
        Image.fromarray(np.roll(image, 7 * i, axis=1)).save(photos / f"f{i}.png")
        cams.append(Camera(np.eye(4, dtype=np.float32), 500.0, 500.0, WIDTH / 2, HEIGHT / 2, WIDTH, HEIGHT, f"f{i}"))
    write_cameras(scene / "cameras.json", cams)
    cmd = [sys.executable, "-m", "qr_cl.app.cli", "features", str(scene), "--images", str(photos), "--clip-weights",
           str(models["clip"]), "--sam-weights", str(models["fast"]), "--crop-layers", "0", "--threads", str(threads),
           "--workers", str(workers)]
    load_before = load_average()
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=folder)
    seconds = time.perf_counter() - start
    if proc.returncode:
        sys.exit(f"qr-cl features --workers {workers} failed:\n{proc.stderr[-3000:]}")
    return {"seconds": seconds, "frames": frames, "seconds_per_frame": seconds / frames,
            "load": [load_before, load_average()]}


def write_models(folder: Path, vit_h: bool) -> dict[str, Path]:
    """Random-weight model files of the real architectures (this checkout's random_models)."""
    from qr_cl.app.features.random_models import (CLIP_ARCHITECTURES, SAM_ARCHITECTURES, random_clip, random_sam,
                                                  save_weights)

    models = {"clip": save_weights(random_clip(CLIP_ARCHITECTURES["ViT-B-16"], seed=1), folder / "open_clip_model.safetensors"),
              "vit_b": save_weights(random_sam(SAM_ARCHITECTURES["vit_b"], seed=2), folder / "sam_vit_b.pth"),
              "fast": save_weights(random_sam(SAM_ARCHITECTURES["mobile_sam"], seed=2), folder / "mobile_sam.pt")}
    if vit_h:
        models["vit_h"] = save_weights(random_sam(SAM_ARCHITECTURES["vit_h"], seed=2), folder / "sam_vit_h.pth")
    return models


def test_image(data: Path | None) -> tuple[np.ndarray, str]:
    """A 640x480 RGB image: a rendered fox view when the data has the fox, else a drawn one."""
    fox = data / "wakufactory-fox" / "fox.ply" if data else None
    if fox is not None and fox.is_file():
        from PIL import Image

        from qr_cl.app.rendering.command import render_views
        from qr_cl.scene import load_ply, orbit_cameras
        g = load_ply(fox)
        out = Path(tempfile.mkdtemp())
        render_views(g, orbit_cameras(g.means, 1, WIDTH, HEIGHT, up_axis=1), out, None)
        return np.asarray(Image.open(out / "000_rgb.png").convert("RGB")), "a rendered fox view"
    yy, xx = np.mgrid[:HEIGHT, :WIDTH]
    return np.stack([xx % 256, yy % 256, (xx + yy) % 256], -1).astype(np.uint8), "a drawn gradient"


def compare(base: Path, this: Path) -> dict:
    """Equal mask ids per level (fraction of pixels) and the smallest cosine of the feature rows."""
    a, b = np.load(base), np.load(this)
    same = [float((a["ids"][i] == b["ids"][i]).mean()) for i in range(len(a["ids"]))]
    if a["features"].shape != b["features"].shape:
        return {"ids_equal": same, "rows": [len(a["features"]), len(b["features"])]}
    fa, fb = a["features"], b["features"]
    cos = (fa * fb).sum(1) / np.maximum(np.linalg.norm(fa, axis=1) * np.linalg.norm(fb, axis=1), 1e-12)
    return {"ids_equal": same, "rows": [len(fa), len(fb)], "cosine_min": float(cos.min()) if len(cos) else 1.0}


def describe_base(base: str | None) -> str | None:
    """The base as the report names it: a checkout by its commit, an interpreter by its path."""
    if base is None or not Path(base).is_dir():
        return base
    head = subprocess.run(["git", "-C", base, "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    return f"checkout of {head.stdout.strip()}" if head.returncode == 0 else "a checkout"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_base_option(parser, required=False)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--cases", nargs="+", default=["vit_b", "fast", "workers", "vit_h"],
                        choices=["vit_b", "vit_h", "fast", "workers", "clip"])
    parser.add_argument("--base-vit-h", action="store_true", help="also time the base's ViT-H frame")
    parser.add_argument("--frames", type=int, default=4, help="frames of the workers case")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data")
    parser.add_argument("--out", type=Path, default=Path("bench/reports/features-rate"))
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(measure_frame(json.loads(args.worker))))
        return
    image, source = test_image(args.data)
    results = {"threads": args.threads, "image": source, "size": [WIDTH, HEIGHT], "cores": os.cpu_count(),
               "machine": platform.processor() or platform.machine(), "base": describe_base(args.base), "cases": {}}
    with tempfile.TemporaryDirectory(prefix="qr-cl-features-rate-") as tmp, installs(args.base) as runs_of:
        tmp = Path(tmp)
        np.save(tmp / "image.npy", image)
        models = write_models(tmp, "vit_h" in args.cases)
        for case in [c for c in args.cases if c != "workers"]:
            sam = models["fast" if case in ("fast", "clip") else case]
            config = {"case": case, "sam": str(sam), "clip": str(models["clip"]), "image": str(tmp / "image.npy"),
                      "threads": args.threads, "crop_layers": 0 if case == "fast" else 1, "crops": 64}
            entry = {}
            for install in runs_of:
                if install is not THIS and (case == "fast" or (case == "vit_h" and not args.base_vit_h)):
                    continue
                entry[install.label] = run_frame(install, {**config, "save": str(tmp / f"{case}-{install.label}.npz")},
                                                 str(tmp))
                print(f"{case} {install.label}: {entry[install.label]}", flush=True)
            if "base" in entry and case != "clip":
                entry["outputs"] = compare(tmp / f"{case}-base.npz", tmp / f"{case}-this.npz")
            results["cases"][case] = entry
            write_report(args.out, results)                                 # each case as it ends
        if "workers" in args.cases:
            results["cases"]["workers"] = {str(w): run_workers(models, image, args.frames, w, args.threads, tmp)
                                           for w in (1, 2)}
            write_report(args.out, results)


def write_report(out: Path, results: dict) -> None:
    out.mkdir(parents=True, exist_ok=True)
    (out / "results.json").write_text(json.dumps(results, indent=1))
    lines = [f"# qr-cl features: seconds per 640x480 frame ({results['threads']} torch threads, CPU)", "",
             f"Machine: {results['machine']}, {results['cores']} cores; image: {results['image']}; base: "
             f"{results['base'] or 'none'}. Random weights of the real architectures (masks are arbitrary). "
             "Load: the 1-minute load average before and after each run. Made by bench/features_rate.py.", ""]
    if set(results["cases"]) - {"workers", "clip"}:
        lines += ["| case | install | seconds per frame | masks per level | load | per stage (s) |",
                  "| --- | --- | ---: | --- | --- | --- |"]
    for case, entry in results["cases"].items():
        if case == "clip":
            lines += ["", "CLIP ViT-B/16 image encoder, 32 crops a batch: " + ", ".join(
                f"{label} {e['seconds_per_crop']:.3f} s per mask crop" for label, e in entry.items()), ""]
        if case in ("workers", "clip"):
            continue
        for label in ("base", "this"):
            if label in entry:
                e = entry[label]
                stages = ", ".join(f"{k} {v:.1f}" for k, v in e["stages"].items())
                lines.append(f"| {case} | {label} | {e['seconds']:.1f} | {e['counts']} | "
                             f"{e['load'][0]:.2f} / {e['load'][1]:.2f} | {stages} |")
        if "base" in entry:
            o = entry["outputs"]
            lines += ["", f"{case}: this checkout is {entry['base']['seconds'] / entry['this']['seconds']:.2f}x the base; "
                      f"equal mask ids per level {', '.join(f'{x:.5f}' for x in o['ids_equal'])}; feature rows "
                      f"{o['rows']}" + (f", smallest cosine {o['cosine_min']:.7f}" if 'cosine_min' in o else ""), ""]
    if "workers" in results["cases"]:
        w = results["cases"]["workers"]
        lines += ["", "`qr-cl features` on a scene of frames, fast profile (MobileSAM, `--crop-layers 0`), "
                  f"`--threads {results['threads']}`:", "", "| workers | frames | seconds | seconds per frame | load |",
                  "| --- | ---: | ---: | ---: | --- |"]
        lines += [f"| {k} | {v['frames']} | {v['seconds']:.1f} | {v['seconds_per_frame']:.1f} | "
                  f"{v['load'][0]:.2f} / {v['load'][1]:.2f} |" for k, v in w.items()]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
