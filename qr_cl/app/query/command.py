"""``qr-cl query``: ask a scene where some text is.

For each query: its per-Gaussian score (relevancy by default, :mod:`.relevancy`) as
``<query>.npy`` [N]; a 3DGS PLY coloured by it (``<query>.ply``); with ``--threshold``, the
Gaussians scoring at least that as their own PLY (``<query>_selected.ply``); and, per view
(named by the camera's index, or ``orbit<i>``), ``views/<view>_<query>.png``, the score rendered
through Q-Render as a heatmap over the grey RGB, beside ``views/<view>_rgb.png``.
``query.json`` sums it up. Query text is looked up as :mod:`.text` describes.
"""
from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ...runtime import DEFAULTS, SAMPLERS
from ...scene import Camera, orbit_cameras
from ..arguments import AXES, nonnegative_int, positive_int
from ..features.classes import recorded_encoder
from ..features.weights import file_sha256
from ..images import save_rgb
from ..process import cap_kernel_threads
from .pictures import heat_colours, overlay, render_rgb, render_values, write_score_ply, write_selection_ply
from .relevancy import METHODS, score, score_range
from .scene import QueryScene, load_query_scene, scene_features
from .text import QueryError, TextEncoder, TextLookup, normalise, open_clip_encoder

#: Views rendered by default: this many of the scene's cameras, evenly spaced (all when fewer).
DEFAULT_VIEWS = 8


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl query``."""
    parser.add_argument("scene", help="scene folder (point_cloud.ply, cameras.json, classes.json) "
                                      "or a .ply/.splat")
    parser.add_argument("queries", nargs="+", help="query texts, e.g. chair \"a wooden table\"")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="GS-Net checkpoint.pt from qr-cl train")
    src.add_argument("--features", help="per-Gaussian features: .npy [N,C] or a PLY with feature_<i> properties")
    parser.add_argument("--out", default="qr-cl-query", help="output folder (default ./qr-cl-query)")
    parser.add_argument("--score", choices=METHODS, default="relevancy",
                        help="relevancy against negative texts in [0,1] (default) or cosine similarity")
    parser.add_argument("--threshold", type=float,
                        help="also write the Gaussians scoring at least this as <query>_selected.ply")
    views = parser.add_mutually_exclusive_group()
    views.add_argument("--views", type=nonnegative_int, nargs="*",
                       help=f"camera indices to render (default: {DEFAULT_VIEWS} evenly spaced cameras)")
    views.add_argument("--orbit", type=positive_int, help=f"render this many orbit views instead (default for a bare "
                                                 f"scene file: {DEFAULT_VIEWS})")
    parser.add_argument("--width", type=positive_int, help="image width in px (rescales cameras; orbit default 640)")
    parser.add_argument("--up-axis", type=int, choices=AXES, default=2, help="world up axis of orbits (2 = z, 1 = y)")
    parser.add_argument("--sampler", choices=SAMPLERS, default=DEFAULTS.sampler,
                        help="renderer of the heatmaps (default quantile)")
    parser.add_argument("-k", type=positive_int, default=DEFAULTS.k, help=f"K of the sampler (default {DEFAULTS.k})")
    parser.add_argument("--clip-weights", help="local OpenCLIP weights file: encodes text the tables lack "
                                               "(needs pip install 'qr-cl[clip]'; nothing is downloaded)")
    parser.add_argument("--clip-model", default="ViT-B-32",
                        help="OpenCLIP architecture of --clip-weights (default ViT-B-32)")
    parser.add_argument("--level", type=nonnegative_int, default=0, help="LangSplat mask level of a scene folder (default 0)")


def file_stem(text: str) -> str:
    """A file name stem for a query text: lower-case letters, digits and underscores."""
    return re.sub(r"[^a-z0-9]+", "_", normalise(text)).strip("_") or "query"


def query_cameras(scene: QueryScene, views: list[int] | None, orbit: int | None, width: int | None,
                  up_axis: int = 2) -> list[tuple[str, Camera]]:
    """(file prefix, camera) of each heatmap view: ``orbit`` orbit views ("orbit000", ...; also
    for a scene without cameras), else the scene's cameras ``views`` (default
    :data:`DEFAULT_VIEWS` evenly spaced; prefix the index, "002"), rescaled to ``width`` px when
    given. QueryError for an index out of range."""
    if orbit is not None or not scene.cameras:
        w = width or DEFAULTS.width
        cams = orbit_cameras(scene.gaussians.means, orbit if orbit is not None else DEFAULT_VIEWS, w,
                             round(w * 3 / 4), up_axis=up_axis)
        return [(f"orbit{i:03d}", c) for i, c in enumerate(cams)]
    count = len(scene.cameras)
    if views is None:
        views = sorted(set(np.linspace(0, count - 1, min(count, DEFAULT_VIEWS)).round().astype(int).tolist()))
    bad = [v for v in views if not 0 <= v < count]
    if bad:
        raise QueryError(f"--views {bad}: the scene has cameras 0..{count - 1}")
    cams = [scene.cameras[v] for v in views]
    if width:
        cams = [c.resized(width, round(c.height * width / c.width)) for c in cams]
    return [(f"{v:03d}", c) for v, c in zip(views, cams)]


def write_query_outputs(scene: QueryScene, scores: dict[str, np.ndarray], lo_hi: dict[str, tuple[float, float]],
                        out: Path, threshold: float | None) -> dict[str, dict]:
    """Per query (keyed by its file stem): ``<stem>.npy``, ``<stem>.ply`` and (``threshold``)
    ``<stem>_selected.ply`` in ``out``; returns {stem: summary}."""
    summary = {}
    for stem, values in scores.items():
        np.save(out / f"{stem}.npy", values)
        write_score_ply(out / f"{stem}.ply", scene.gaussians, values, *lo_hi[stem])
        entry = {"npy": f"{stem}.npy", "ply": f"{stem}.ply", "min": float(values.min()),
                 "max": float(values.max()), "mean": float(values.mean())}
        if threshold is not None:
            selected = values >= threshold
            write_selection_ply(out / f"{stem}_selected.ply", scene.gaussians, selected)
            entry.update(selected_ply=f"{stem}_selected.ply", selected=int(selected.sum()))
        summary[stem] = entry
    return summary


def write_heatmaps(scene: QueryScene, scores: dict[str, np.ndarray], lo_hi: dict[str, tuple[float, float]],
                   cameras: list[tuple[str, Camera]], out: Path, sampler: str, k: int) -> list[Path]:
    """``<view>_rgb.png`` and ``<view>_<stem>.png`` (the scores rendered through ``sampler``
    as a heatmap over the grey RGB) per (prefix, camera) of ``cameras`` into ``out``; returns
    the files written."""
    out.mkdir(parents=True, exist_ok=True)
    stems = list(scores)
    table = np.stack([scores[s] for s in stems], 1)
    files = []
    for view, cam in tqdm(cameras, desc="heatmaps", unit="view"):
        rendered, _ = render_values(scene.gaussians, table, cam, sampler, k)
        rgb, alpha = render_rgb(scene.gaussians, cam)
        files.append(out / f"{view}_rgb.png")
        save_rgb(files[-1], rgb)
        for j, stem in enumerate(stems):
            files.append(out / f"{view}_{stem}.png")
            save_rgb(files[-1], overlay(rgb, heat_colours(rendered[..., j], *lo_hi[stem]), alpha))
    return files


def check_text_encoder(classes: Path, weights: str) -> None:
    """QueryError when ``classes`` (a classes.json written by ``qr-cl features``) records another
    text encoder than the weights file ``weights``: its text features and the encoder's would be
    in different spaces."""
    recorded = recorded_encoder(classes)
    if recorded and Path(weights).is_file() and recorded.get("sha256") != file_sha256(weights):
        raise QueryError(f"{weights}: not the CLIP that made {classes} ({recorded.get('model')}, "
                         f"{recorded.get('weights')}); its text features would not match")


def run(args: argparse.Namespace, encoder: TextEncoder | None = None) -> int:
    """Score, render and write every query (module docstring); ``encoder`` replaces the one
    ``--clip-weights`` loads (tests inject a stub). Bad queries: one line, exit status 2."""
    try:
        return _run(args, encoder)
    except QueryError as exc:
        print(f"qr-cl: error: {exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace, encoder: TextEncoder | None) -> int:
    cap_kernel_threads()
    scene = load_query_scene(args.scene, args.level)
    if args.clip_weights:
        check_text_encoder(Path(args.scene) / "classes.json", args.clip_weights)
    if encoder is None and args.clip_weights:
        encoder = open_clip_encoder(args.clip_weights, args.clip_model)
    cameras = query_cameras(scene, args.views, args.orbit, args.width, args.up_axis)
    features = scene_features(scene, args.checkpoint, args.features)
    lookup = TextLookup(features.shape[1], scene.classes, encoder)
    queries = {}
    for text in args.queries:
        stem = file_stem(text)
        stem = stem if stem not in queries else f"{stem}_{len(queries)}"
        queries[stem] = lookup(text)                                  # every text known before any work
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scores = {stem: score(features, lookup, q, args.score) for stem, q in queries.items()}
    lo_hi = {stem: score_range(v) for stem, v in scores.items()}
    summary = write_query_outputs(scene, scores, lo_hi, out, args.threshold)
    write_heatmaps(scene, scores, lo_hi, cameras, out / "views", args.sampler, args.k)
    for stem, q in queries.items():
        summary[stem].update(text=q.text, source=q.source, score=args.score)
    (out / "query.json").write_text(json.dumps({"scene": str(args.scene), "score": args.score,
                                                "views": len(cameras), "queries": summary}, indent=1))
    for stem, s in summary.items():
        chosen = f", {s['selected']} >= {args.threshold}" if args.threshold is not None else ""
        print(f"{s['text']!r} ({s['source']}): {args.score} {s['min']:.3f}..{s['max']:.3f}, "
              f"mean {s['mean']:.3f}{chosen} -> {out / s['ply']}")
    print(f"{len(cameras)} views of heatmaps in {out / 'views'}; summary {out / 'query.json'}")
    return 0
