"""``qr-cl demo``: the embedded default job, end to end on synthetic labelled rooms.

1. Generates (or reuses from the cache) ``--train-scenes`` training rooms and one held-out room
   (:mod:`qr_cl.synthetic`; their "CLIP" features are simulated).
2. Trains GS-Net through Q-Render (K=40) on the training rooms; the first ``--short-steps`` of
   that run double as the Q-Render K=40 entry of the renderer comparison.
3. Short runs of the same budget with Q-Render K=5, top-K K=5 and K=40, and V-Render.
4. The per-scene baseline (free per-Gaussian features) fitted on the held-out room and on a
   training room with the main run's budget.
5. Evaluates every model on the held-out room and on a training room (mIoU/mAcc, 19/15/10 classes)
   and writes ``report.md``, ``results.json`` and images into ``--out``.

The default budget (480 main / 160 comparison steps) spends about the time the demo took when a
training step still computed every Gaussian's features (120 / 40 steps then, ~6 minutes on 2
cores) on 4x the training.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from .baseline import fit_free_features
from .data import load_scene_folder
from .evaluate import evaluate_features, ground_truth, markdown_table, network_features, write_visuals
from .model import cap_kernel_threads, torch_threads
from .synthetic import STYLES, SyntheticConfig, synthetic_scene
from .train import TrainConfig, train


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl demo``."""
    parser.add_argument("--out", default="qr-cl-demo", help="report folder (default ./qr-cl-demo)")
    parser.add_argument("--cache", help="scene cache (default $QR_CL_CACHE/scenes or ~/.cache/qr-cl/scenes)")
    parser.add_argument("--train-scenes", type=int, default=4, help="training rooms (default 4)")
    parser.add_argument("--gaussians", type=int, default=24000, help="Gaussians per room (default 24000)")
    parser.add_argument("--style", choices=STYLES, default="flat",
                        help="rooms of flat opaque Gaussians (default) or 3DGS-like semi-transparent shells "
                             "(qr_cl/app/synthetic.py; 60000 Gaussians suit them)")
    parser.add_argument("--steps", type=int, default=480, help="steps of the main run and the baseline (default 480)")
    parser.add_argument("--short-steps", type=int, default=160,
                        help="steps of the renderer comparison runs (default 160)")
    parser.add_argument("--rays", type=int, default=2048, help="rays per view (default 2048)")
    parser.add_argument("--views", type=int, default=4, help="views per step (default 4)")
    parser.add_argument("--seed", type=int, default=0)


def _train(cfg, resume: bool = False) -> tuple[dict, float]:
    start = time.perf_counter()
    trainer = train(cfg, resume=resume)
    return trainer.state(), time.perf_counter() - start


def run(args: argparse.Namespace) -> int:
    """Run the demo (module docstring) and print where the report is."""

    cap_kernel_threads(1)                     # before the first render (scene generation)
    t0 = time.perf_counter()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(args.cache) if args.cache else None
    seeds = list(range(args.seed, args.seed + args.train_scenes))
    held_seed = args.seed + 1000
    paths = [synthetic_scene(SyntheticConfig(seed=s, n_gaussians=args.gaussians, style=args.style), cache)
             for s in seeds + [held_seed]]
    train_paths, held_path = [str(p) for p in paths[:-1]], str(paths[-1])
    print(f"scenes: {len(train_paths)} training rooms + 1 held-out room ({args.gaussians} Gaussians each) in "
          f"{paths[0].parent} ({time.perf_counter() - t0:.0f} s)")
    eval_scenes = {"held-out": load_scene_folder(held_path), "training": load_scene_folder(train_paths[0])}
    truths = {split: ground_truth(s) for split, s in eval_scenes.items()}
    gts = {split: labels for split, (labels, _) in truths.items()}
    truth_text = ("by App. B from the labelled point cloud" if truths["held-out"][1] == "points"
                  else "the generator's per-Gaussian labels (opacity >= 0.1)")

    def cfg(name: str, steps: int, sampler: str = "quantile", k: int = 40) -> TrainConfig:
        return TrainConfig(scenes=train_paths, out=str(out / "runs" / name), steps=steps, views=args.views,
                           rays=args.rays, sampler=sampler, k=k, seed=args.seed, checkpoint_every=steps)

    rows, timings = [], {}

    def score(method: str, renderer: str, steps: int, features_of) -> None:
        for split, scene in eval_scenes.items():
            metrics = evaluate_features(scene, features_of(scene), gts[split])
            rows.append({"method": f"{method} / {renderer} / {steps} steps", "scene": scene.name,
                         "split": split, "metrics": metrics})

    with torch_threads(1):
        runs = [("quantile", 40, "Q-Render K=40"), ("quantile", 5, "Q-Render K=5"), ("topk", 40, "top-K K=40"),
                ("topk", 5, "top-K K=5"), ("volume", 0, "V-Render")]
        states = {}
        for sampler, k, label in runs:
            states[label], timings[f"GS-Net {label}, {args.short_steps} steps"] = _train(
                cfg("gsnet-q40" if label == "Q-Render K=40" else f"short-{sampler}{k}", args.short_steps, sampler, k or 40))
            score("GS-Net", label, args.short_steps, lambda s, st=states[label]: network_features(st, s))
        main_state, seconds = _train(cfg("gsnet-q40", args.steps), resume=True)
        timings[f"GS-Net Q-Render K=40, steps {args.short_steps}->{args.steps}"] = seconds
        score("GS-Net", "Q-Render K=40", args.steps, lambda s: network_features(main_state, s))
        baseline = {}
        for split, scene in eval_scenes.items():
            start = time.perf_counter()
            bcfg = cfg("baseline", args.steps)
            baseline[scene.name] = fit_free_features(scene, bcfg)
            timings[f"per-scene baseline ({split} room), {args.steps} steps"] = time.perf_counter() - start
        score("per-scene baseline", "Q-Render K=40", args.steps, lambda s: baseline[s.name])
        images = []
        for split, scene in eval_scenes.items():
            images += write_visuals(scene, network_features(main_state, scene), gts[split],
                                    out / "images" / "gsnet", views=(0, 1))
            images += write_visuals(scene, baseline[scene.name], gts[split], out / "images" / "baseline", views=(0, 1))

    wall = time.perf_counter() - t0
    table = markdown_table(rows)
    (out / "results.json").write_text(json.dumps({"rows": rows, "timings_s": timings, "wall_s": wall,
                                                  "args": vars(args)}, indent=1, default=str))
    pngs = [p for p in images if p.suffix == ".png"]
    report = ["# qr-cl demo", "",
              f"GS-Net (small sparse UNet) trained on {len(train_paths)} synthetic rooms; evaluated on a held-out "
              f"room ({Path(held_path).name}) and a training room ({Path(train_paths[0]).name}). The \"CLIP\" "
              "features are simulated (class prototypes plus noise; see qr_cl/synthetic.py). mIoU/mAcc in % over "
              f"the classes present, ground truth {truth_text}.", "", table, "",
              "## Wall times", "", "| run | s |", "| --- | ---: |"]
    report += [f"| {k} | {v:.1f} |" for k, v in timings.items()] + [f"| whole demo | {wall:.1f} |", "", "## Images",
               "", "Each picture: RGB | PCA of the rendered features | predicted classes | ground truth "
               "(labelled Gaussians only); colours in images/*/legend.md.", ""]
    report += [f"![{p.stem}]({p.relative_to(out)})" for p in pngs]
    (out / "report.md").write_text("\n".join(report) + "\n")
    print(table)
    print(f"demo finished in {wall:.0f} s. Report: {(out / 'report.md').resolve()}")
    return 0
