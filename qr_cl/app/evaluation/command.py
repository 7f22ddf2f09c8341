"""``qr-cl eval``: 3D open-vocabulary segmentation of Gaussians, mIoU/mAcc tables, images, PLYs.

Prediction per Gaussian: the class (of the evaluated subset) whose text feature has the highest
cosine similarity with the Gaussian's feature (:mod:`qr_cl.app.evaluation.scoring`). Ground
truth: per-Gaussian labels, or (preferred when present) pseudo labels from a labelled point cloud
by paper App. B (:mod:`qr_cl.app.evaluation.labels`). Gaussians with opacity < 0.1 and labels
outside the subset are ignored (:data:`qr_cl.app.evaluation.labels.MIN_OPACITY`).
"""
from __future__ import annotations

import argparse
import difflib
import json
import warnings
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..arguments import nonnegative_int, positive_float, positive_int
from ..process import torch_threads
from ..scenes.folders import NO_LANGUAGE, load_scene_folder
from ..training.network import load_checkpoint, network_features
from .labels import ground_truth
from .scoring import evaluate_features, markdown_table
from .visuals import frame_cameras, write_visuals


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl eval``."""
    parser.add_argument("scenes", nargs="+", help="scene folders with classes.json and ground truth")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="GS-Net checkpoint.pt from qr-cl train")
    src.add_argument("--features", help="per-Gaussian features .npy [N,C] (one scene)")
    parser.add_argument("--out", required=True, help="output folder (results.json, results.md, images/)")
    parser.add_argument("--gt", choices=("auto", "points", "gaussians"), default="auto",
                        help="ground truth: App. B from labels/points.ply, labels/gaussian_labels.npy, or auto")
    parser.add_argument("--knn", type=positive_int, default=5, help="App. B neighbours (default 5)")
    parser.add_argument("--max-mahalanobis", type=positive_float, default=0.1, help="App. B distance cut (default 0.1)")
    parser.add_argument("--views", type=nonnegative_int, nargs="*", default=[0], help="frames to render images of (default 0)")
    parser.add_argument("--query", help="class name whose relevancy the images show (default: the most "
                                        "common labelled class other than wall and floor)")
    parser.add_argument("--level", type=nonnegative_int, default=0, help="LangSplat mask level (default 0)")


def run(args: argparse.Namespace) -> int:
    """Evaluate every scene, write results.json / results.md and the images; print the table."""

    if args.features and len(args.scenes) != 1:
        raise SystemExit("qr-cl eval: --features evaluates exactly one scene")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = load_checkpoint(args.checkpoint) if args.checkpoint else None
    if args.features and not Path(args.features).is_file():
        raise FileNotFoundError(2, "no such features file (--features)", args.features)
    rows = []
    for path in tqdm(args.scenes, desc="eval", unit="scene"):
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", f".*{NO_LANGUAGE}")  # frames without language features are fine here
            scene = load_scene_folder(path, args.level, require_language=False)
        if args.query and scene.classes is not None and args.query not in scene.classes.names:
            close = difflib.get_close_matches(args.query, scene.classes.names, n=3, cutoff=0.5)
            raise SystemExit(f"qr-cl eval: --query {args.query!r} is not a class of {scene.root / 'classes.json'}"
                             f" (closest: {', '.join(close) if close else 'none'})")
        with torch_threads(1):
            feats = network_features(ckpt, scene) if ckpt is not None else np.load(args.features).astype(np.float32)
        gt, source = ground_truth(scene, args.gt, args.knn, args.max_mahalanobis)
        metrics = evaluate_features(scene, feats, gt)
        with torch_threads(1):
            write_visuals(scene, feats, gt, out / "images", frame_cameras(scene, args.views), args.query)
        rows.append({"method": "GS-Net" if ckpt is not None else Path(args.features).name, "scene": scene.name,
                     "split": "-", "gt": source, "metrics": metrics})
    means = {s: {k: float(np.nanmean([r["metrics"][s][k] for r in rows])) for k in ("miou", "macc")}
             for s in (19, 15, 10)}
    rows_md = rows + ([{"method": rows[0]["method"], "scene": "mean", "split": "-", "metrics": means}]
                      if len(rows) > 1 else [])
    (out / "results.json").write_text(json.dumps({"scenes": rows, "mean": means}, indent=1))
    text = markdown_table(rows_md)
    (out / "results.md").write_text(text)
    print(text + f"\nresults: {out.resolve() / 'results.md'} (and results.json, images/)")
    return 0
