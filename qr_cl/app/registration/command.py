"""``qr-cl register``: Dr.Splat's training-free registration of a scene folder's mask features onto
its Gaussians (:mod:`.register`): ``features.npy`` [N,C] (zero rows: Gaussians no masked pixel
picks) and ``registration.json`` (K, levels, Gaussians reached, rays, time; mIoU/mAcc when the
folder has classes and ground truth). ``qr-cl eval --features`` and ``qr-cl query --features``
read the features."""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np

from ..arguments import positive_int
from ..evaluation.labels import ground_truth
from ..evaluation.scoring import evaluate_features, markdown_table
from ..process import cap_kernel_threads
from ..scenes.folders import load_scene_folder
from .register import CHUNK_RAYS, DRSPLAT_K, register, scene_views

#: LangSplat's mask levels (default, small, medium, large): ``--levels all``.
ALL_LEVELS = (0, 1, 2, 3)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl register``."""
    parser.add_argument("scene", help="scene folder (point_cloud.ply, cameras.json, language_features/)")
    parser.add_argument("--out", required=True, help="output folder (features.npy, registration.json)")
    parser.add_argument("-k", type=positive_int, default=DRSPLAT_K,
                        help=f"top contributors per pixel, by weight alpha*T (default {DRSPLAT_K})")
    parser.add_argument("--levels", nargs="+", default=["0"],
                        help="LangSplat mask levels to register, summed (default 0; 'all' for 0 1 2 3)")
    parser.add_argument("--chunk-rays", type=positive_int, default=CHUNK_RAYS,
                        help=f"pixels per selection, bounding memory (default {CHUNK_RAYS})")


def parse_levels(values: list[str]) -> list[int]:
    """``--levels`` as level indices: 'all' for :data:`ALL_LEVELS`, else some of them."""
    if values == ["all"]:
        return list(ALL_LEVELS)
    if not all(v.isdigit() and int(v) in ALL_LEVELS for v in values):
        raise SystemExit(f"qr-cl register: --levels takes levels of {' '.join(map(str, ALL_LEVELS))} or 'all', "
                         f"got {' '.join(values)}")
    return sorted({int(v) for v in values})


def save_npy_atomic(path: Path, array: np.ndarray) -> None:
    """np.save to ``path`` through a temporary file renamed over it (never a half-written file)."""
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.npy")
    np.save(tmp, array)
    os.replace(tmp, path)


def run(args: argparse.Namespace) -> int:
    """Register the scene, write features.npy and registration.json, print the summary (and the
    scores, when the scene has ground truth)."""
    cap_kernel_threads()
    levels = parse_levels(args.levels)
    scenes = [load_scene_folder(args.scene, level) for level in levels]
    scene = scenes[0]
    result = register(scene.gaussians, scene_views(scenes), args.k, args.chunk_rays, total=len(scene.frames))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    save_npy_atomic(out / "features.npy", result.features)
    summary = {"scene": str(scene.root.resolve()), "levels": levels, **result.summary()}
    print(f"registered {summary['views']} views ({summary['rays']} masked pixels, K={args.k}) onto "
          f"{summary['reached']} of {summary['gaussians']} Gaussians in {summary['seconds']:.1f} s; the other "
          f"{summary['gaussians'] - summary['reached']} keep no feature (scored unlabelled)")
    if scene.classes is not None and (scene.gaussian_labels is not None or scene.points is not None):
        gt, source = ground_truth(scene)
        metrics = evaluate_features(scene, result.features, gt)
        summary["metrics"] = {s: {k: m[k] for k in ("miou", "macc", "unlabelled")} for s, m in metrics.items()}
        summary["gt"] = source
        print(markdown_table([{"method": f"Dr.Splat registration K={args.k}", "scene": scene.name, "split": "-",
                               "metrics": metrics}]))
    tmp = out / f".registration.json.tmp{os.getpid()}"
    tmp.write_text(json.dumps(summary, indent=1))
    os.replace(tmp, out / "registration.json")
    print(f"features: {(out / 'features.npy').resolve()}")
    return 0
