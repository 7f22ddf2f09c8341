"""``qr-cl reproduce``: the paper's controlled experiments on 3DGS-like synthetic rooms, one command.

1. Scenes: seeded "3dgs"-style rooms (:mod:`qr_cl.app.scenes.synthetic`: thick semi-transparent shells,
   anisotropic Gaussians, floaters; cached), compared with the real captures of ``--data`` (the
   fox, the donut), the demo's flat rooms and the dense indoor room of :mod:`qr_cl.app.scenes.procedural`
   by their opacity histograms and V-Render entries per pixel (Gaussians blended per ray).
2. GS-Net trained on the training rooms with the same budget through every renderer of the plan
   (V-Render, top-K and Q-Render over K, Stratified-K), and through Q-Render K=40 on rooms whose
   opacity logits carry Gaussian noise, each with ``plan.seeds`` seeds; held-out mIoU/mAcc
   (19/15/10 classes), over all labelled Gaussians and over those the room's views reach.
   Table 2's per-scene rows on the held-out room itself, scored the same way: GS-Net overfit to
   it (the same network, budget and seeds), Dr.Splat's training-free registration
   (:mod:`qr_cl.app.registration`) and free features fitted through the renderer (no 3D term).
   Per-class IoU of those models (first seed), the main run's (Q-Render K=40) confusion matrix,
   and pictures with the models side by side.
3. The rendering time of every renderer on the held-out room (512-D features, whole images).
4. The transmittance profiles along sample rays (Fig. 3) and their mean gap to V-Render's, and
   each renderer's feature image compared with V-Render's (cosine similarity); where top-K's and
   Q-Render's K=5 picks lie along the rays of the room and of the real captures, and how the
   weight spreads in depth (:mod:`qr_cl.app.experiments.ray_depth`).
5. RGB fidelity: PSNR of Q-Render against V-Render from SH colours: the raw normalized
   Q-Render image, Q-Render's colour times V-Render's alpha and times its own alpha (and top-K's
   colour times V-Render's alpha), with pictures.
6. ``report.md`` (Table 2's shape with the paper's numbers beside ours, tables with mean and
   spread over the seeds, the paper's claims judged by them: reproduced, not reproduced or
   undecided, each with the difference its seeds resolve; :mod:`qr_cl.app.experiments.claims`,
   :mod:`qr_cl.app.experiments.table2`),
   ``results.json`` and the plots, in ``--out``.

One module per study in :mod:`qr_cl.app.experiments`; this module runs them in turn.

Plans (:data:`PLANS`): "full", "quick" (``--quick``: fewer renderers and noise levels, the
budget chosen by measurement: see :mod:`qr_cl.app.experiments.plan`) and "smoke" (``--smoke``,
seconds on tiny rooms: checks the wiring, its numbers mean nothing); the report states each one's
wall time.
"""
from __future__ import annotations

import argparse
import json
import os
from dataclasses import asdict
from pathlib import Path

from tqdm import tqdm

from ...runtime import runtime
from ..arguments import nonnegative_int
from ..evaluation.labels import ground_truth, reached_gaussians
from ..process import cap_kernel_threads, keep_freed_memory, release_freed_memory, torch_threads
from ..scenes.folders import load_scene_folder
from ..scenes.room_config import FEATURE_FIELDS, SyntheticConfig
from ..scenes.synthetic import room_folder
from ..timing import Stopwatch
from ..training.network import network_features
from .agreement import feature_agreement
from .claims import paper_claims
from .depth_rooms import depth_room_study
from .plan import NOISE_K, PLANS, Plan, plan_runs
from .ray_depth import ray_depth_study
from .render_times import render_times
from .report import write_report
from .rgb import rgb_study
from .rooms import splat_rooms
from .scene_statistics import compare_scenes
from .segmentation import segmentation_study
from .table2 import table2_claims, table2_lines, table2_stats
from .training_runs import free_feature_scores, overfit_scores, registration_scores, train_and_evaluate
from .transmittance import transmittance_study


def run_reproduction(plan: Plan, mode: str, out: Path, cache: Path | None, data: Path | None, seed: int,
                     features: str = "clip") -> dict:
    """Run every experiment of ``plan`` (module docstring) on rooms of the feature model
    ``features``, write the report into ``out`` and return the results."""
    watch = Stopwatch()
    out.mkdir(parents=True, exist_ok=True)
    train_paths, held_path = splat_rooms(plan, seed, cache, features)
    held = load_scene_folder(held_path)
    gt, _ = ground_truth(held)
    flat = load_scene_folder(room_folder(SyntheticConfig(seed=seed + 1000, features=features, **plan.flat_room),
                                         cache))
    statistics = compare_scenes(plan, held, flat, data, seed)
    reached = reached_gaussians(held, "quantile", NOISE_K)
    runs = plan_runs(plan)
    rows = []
    with torch_threads(1):
        for run in tqdm(runs, desc="renderers", unit="run"):
            rows.append(train_and_evaluate(plan, run, train_paths, held, gt, reached, out, seed))
            release_freed_memory()              # each run's peak, not the sum of what the runs left behind
        overfit = [overfit_scores(plan, held, gt, reached, out, seed + s) for s in range(plan.seeds)]
        release_freed_memory()
        free, first_free = [], None
        for s in range(plan.seeds):
            scores, fitted = free_feature_scores(plan, held, gt, reached, out, seed + s)
            free.append(scores)
            first_free = fitted if first_free is None else first_free
            release_freed_memory()
        drsplat, registered = registration_scores(plan, held, gt, reached)
        main = next(r for r in rows if (r["sampler"], r["k"], r["noise"], r["seed"]) == ("quantile", NOISE_K, 0.0, 0))
        models = {"GS-Net generalised": network_features(Path(main["checkpoint"]), held),
                  "GS-Net overfit": network_features(Path(overfit[0]["checkpoint"]), held),
                  "Dr.Splat registration": registered, "free features": first_free}
        segmentation = segmentation_study(held, models, gt, out, f"GS-Net {main['label']}, seed {seed}")
        depth_rooms = depth_room_study(plan, seed, cache, features, out)
        release_freed_memory()
        volume = next(r for r in rows if r["sampler"] == "volume")
        timed_features = network_features(Path(volume["checkpoint"]), held)      # timed renders: V-Render's GS-Net
    timed = [r for r in runs if not r.noise and not r.seed]
    mask_accuracy = {p.name: json.loads((p / "synthetic.json").read_text())["mask_accuracy19"]
                     for p in [*train_paths, held.root]}
    results = {"mode": mode, "plan": asdict(plan), "seed": seed, "features": features,
               "device": runtime().device.name.strip(), "mask_accuracy19": mask_accuracy,
               "scenes": {"train": [p.name for p in train_paths], "held_out": held.name},
               "statistics": statistics, "runs": rows, "overfit": overfit, "free_features": free,
               "drsplat": [drsplat],
               "reached": {"gaussians": int((reached & (gt >= 0)).sum()), "labelled": int((gt >= 0).sum())},
               "segmentation": segmentation,
               "render_ms": render_times(plan, held, timed_features, timed),
               "agreement": feature_agreement(plan, held, timed_features, timed),
               "profiles": transmittance_study(plan, held, out, seed),
               "ray_depths": ray_depth_study(plan, held, data, seed), "depth_rooms": depth_rooms,
               "rgb": rgb_study(plan, held, data, out)}
    results["claims"] = table2_claims(results) + paper_claims(results)
    results["wall_s"] = watch.seconds
    write_report(out, results)
    return results


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl reproduce``."""
    parser.add_argument("--quick", action="store_true",
                        help="the quick plan: V-Render, top-K K=5, Q-Render K in {5, 40}, Stratified-K K=40, noise "
                             "{0, 0.5}, 300 steps, 12 training rooms, 3 seeds; Table 2's rows; top-K against Q-Render "
                             "at K=5 on rooms with the depth structure")
    parser.add_argument("--features", choices=tuple(FEATURE_FIELDS), default="clip",
                        help="simulated CLIP features around the real CLIP text embeddings of the class names "
                             "(default), or random nearly orthogonal class prototypes (earlier releases)")
    parser.add_argument("--smoke", action="store_true", help="seconds on tiny rooms (tests; numbers mean nothing)")
    parser.add_argument("--out", default="qr-cl-reproduce", help="report folder (default ./qr-cl-reproduce)")
    parser.add_argument("--cache", help="scene cache (default $QR_CL_CACHE/scenes or ~/.cache/qr-cl/scenes)")
    parser.add_argument("--data", default=os.environ.get("QR_CL_DATA"),
                        help="folder with the real scenes (wakufactory-fox/fox.ply, v3dg-donut/donut_fused.ply; "
                             "default $QR_CL_DATA): compared with the synthetic rooms and used for RGB fidelity")
    parser.add_argument("--seed", type=nonnegative_int, default=0)


def run(args: argparse.Namespace) -> int:
    """``qr-cl reproduce``: run the plan and print the report's path and claims."""
    cap_kernel_threads()                      # before the first render (scene generation)
    keep_freed_memory()
    mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    out = Path(args.out)
    if args.data and not Path(args.data).is_dir():
        raise FileNotFoundError(2, "no such folder (--data)", args.data)
    results = run_reproduction(PLANS[mode], mode, out, Path(args.cache) if args.cache else None,
                               Path(args.data) if args.data else None, args.seed, args.features)
    print("\n".join(["Table 2 (held-out room, mIoU/mAcc in %; paper's rows in italics):",
                     *table2_lines(table2_stats(results)), ""]))
    for c in results["claims"]:
        print(f"{c['verdict']:>15}: {c['claim']} ({c['measured']}; seeds resolve {c['resolution']})")
    print(f"reproduce ({mode}) finished in {results['wall_s']:.0f} s. Report: {(out / 'report.md').resolve()}")
    return 0
