"""``qr-cl demo``: the embedded default job, end to end on synthetic labelled rooms.

1. Generates (or reuses from the cache) ``--train-scenes`` training rooms and one held-out room
   (:mod:`qr_cl.app.scenes.synthetic`, "3dgs" style by default: semi-transparent shells, anisotropic
   Gaussians and floaters, where a ray blends about 90 Gaussians; their "CLIP" features are
   simulated around the real CLIP text embeddings of the class names, ``--features orthogonal``
   for random class prototypes).
2. Trains GS-Net through Q-Render (K=40) on the training rooms; the first ``--short-steps`` of
   that run double as the Q-Render K=40 entry of the renderer comparison.
3. Short runs of the same budget with Q-Render K=5, top-K K=5 and K=40, and V-Render.
4. Table 2's per-scene methods on the held-out room itself: GS-Net overfit to it (the main run's
   network and budget), free features fitted through the renderer (no 3D term) with that budget,
   and Dr.Splat's training-free registration (:mod:`qr_cl.app.registration`).
5. Evaluates the GS-Net runs on the held-out room and on a training room, the per-scene methods on
   the held-out room (mIoU/mAcc, 19/15/10 classes; mIoU19 also over the Gaussians the views
   reach, all a per-scene fit can learn) and writes ``report.md`` (Table 2's rows for this one
   seed with the paper's beside them, the renderer comparison), ``results.json`` and pictures
   (the held-out room's predictions of the four models side by side) into ``--out``.

The default budget (720 main / 240 comparison steps on 60k-Gaussian rooms) was chosen to keep
the demo well within 10 minutes on 2 cores.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ..arguments import nonnegative_int, positive_int
from ..evaluation.labels import ground_truth, reached_gaussians
from ..evaluation.scoring import evaluate_features, markdown_table
from ..evaluation.visuals import PANEL_SIZE, write_comparison, write_visuals
from ..experiments.claims import Stat
from ..experiments.table2 import COLUMNS, ROWS_TEXT, table2_lines
from ..process import cap_kernel_threads, keep_freed_memory, release_freed_memory, torch_threads
from ..registration.register import DRSPLAT_K, register, scene_views
from ..scenes.folders import load_scene_folder
from ..scenes.room_config import FEATURE_FIELDS, STYLES, SyntheticConfig
from ..scenes.synthetic import room_folder
from ..scenes.views import room_overview_cameras
from ..timing import Stopwatch
from ..training.config import TrainConfig
from ..training.free_features import fit_free_features
from ..training.network import network_features
from ..training.trainer import train

#: Gaussians per room of each synthetic style (the default of ``--gaussians``).
ROOM_GAUSSIANS = {"3dgs": 60000, "flat": 24000}
#: Table 2's rows in the demo, in the order its pictures show them.
TABLE2_ROWS = ("GS-Net generalised", "Dr.Splat registration", "GS-Net overfit", "free features")
#: The renderers compared with the short budget: (sampler, K, label); the first is the main run's.
COMPARED = (("quantile", 40, "Q-Render K=40"), ("quantile", 5, "Q-Render K=5"), ("topk", 40, "top-K K=40"),
            ("topk", 5, "top-K K=5"), ("volume", 0, "V-Render"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl demo``."""
    parser.add_argument("--out", default="qr-cl-demo", help="report folder (default ./qr-cl-demo)")
    parser.add_argument("--cache", help="scene cache (default $QR_CL_CACHE/scenes or ~/.cache/qr-cl/scenes)")
    parser.add_argument("--train-scenes", type=positive_int, default=4, help="training rooms (default 4)")
    parser.add_argument("--style", choices=STYLES, default="3dgs",
                        help="3DGS-like rooms: semi-transparent shells of anisotropic Gaussians and floaters "
                             "(default), or the flat opaque rooms of earlier releases (qr_cl/app/scenes/synthetic.py)")
    parser.add_argument("--features", choices=tuple(FEATURE_FIELDS), default="clip",
                        help="simulated CLIP features around the real CLIP text embeddings of the class names "
                             "(default), or random nearly orthogonal class prototypes (earlier releases)")
    parser.add_argument("--gaussians", type=positive_int,
                        help="Gaussians per room (default: " + ", ".join(f"{n} for {s} rooms" for s, n in
                                                                        ROOM_GAUSSIANS.items()) + ")")
    parser.add_argument("--steps", type=positive_int, default=720,
                        help="steps of the main run, of GS-Net overfit and of the free features (default 720)")
    parser.add_argument("--short-steps", type=positive_int, default=240,
                        help="steps of the renderer comparison runs (default 240)")
    parser.add_argument("--rays", type=positive_int, default=2048, help="rays per view (default 2048)")
    parser.add_argument("--views", type=positive_int, default=4, help="views per step (default 4)")
    parser.add_argument("--seed", type=nonnegative_int, default=0)


def _train(cfg: TrainConfig, resume: bool = False) -> tuple[dict, float]:
    """(the trained state, seconds) of a run of ``cfg``."""
    watch = Stopwatch()
    trainer = train(cfg, resume=resume)
    return trainer.state(), watch.seconds


def run(args: argparse.Namespace) -> int:
    """Run the demo (module docstring) and print where the report is."""

    cap_kernel_threads()                      # before the first render (scene generation)
    keep_freed_memory()
    wall_clock = Stopwatch()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    cache = Path(args.cache) if args.cache else None
    seeds = list(range(args.seed, args.seed + args.train_scenes))
    held_seed = args.seed + 1000
    n_gaussians = args.gaussians or ROOM_GAUSSIANS[args.style]
    paths = [room_folder(SyntheticConfig(seed=s, n_gaussians=n_gaussians, style=args.style,
                                         features=args.features), cache)
             for s in seeds + [held_seed]]
    mask_accuracy = [json.loads((p / "synthetic.json").read_text())["mask_accuracy19"] for p in paths]
    train_paths, held_path = [str(p) for p in paths[:-1]], str(paths[-1])
    print(f"scenes: {len(train_paths)} training rooms + 1 held-out room ({n_gaussians} Gaussians each, "
          f"{args.style} style) in {paths[0].parent} ({wall_clock.seconds:.0f} s)")
    eval_scenes = {"held-out": load_scene_folder(held_path), "training": load_scene_folder(train_paths[0])}
    truths = {split: ground_truth(s) for split, s in eval_scenes.items()}
    gts = {split: labels for split, (labels, _) in truths.items()}
    reached = {split: np.where(reached_gaussians(s, "quantile", 40), gts[split], -1)
               for split, s in eval_scenes.items()}
    truth_text = ("by App. B from the labelled point cloud" if truths["held-out"][1] == "points"
                  else "the generator's per-Gaussian labels (opacity >= 0.1)")

    def cfg(name: str, steps: int, sampler: str = "quantile", k: int = 40, scenes: list[str] = train_paths
            ) -> TrainConfig:
        return TrainConfig(scenes=scenes, out=str(out / "runs" / name), steps=steps, views=args.views,
                           rays=args.rays, sampler=sampler, k=k, seed=args.seed, checkpoint_every=steps)

    rows, timings = [], {}

    def score(method: str, renderer: str, steps: str, features_of, splits=tuple(eval_scenes)) -> None:
        """Score a model on the rooms of ``splits``, then give back the memory it and its training freed."""
        for split in splits:
            scene = eval_scenes[split]
            features = features_of(scene)
            rows.append({"method": f"{method} / {renderer} / {steps}", "scene": scene.name,
                         "split": split, "metrics": evaluate_features(scene, features, gts[split]),
                         "reached": evaluate_features(scene, features, reached[split], (19,))[19]})
        release_freed_memory()

    held = eval_scenes["held-out"]
    with torch_threads(1):
        states = {}
        for sampler, k, label in COMPARED:
            states[label], timings[f"GS-Net {label}, {args.short_steps} steps"] = _train(
                cfg("gsnet-q40" if label == "Q-Render K=40" else f"short-{sampler}{k}", args.short_steps, sampler, k or 40))
            score("GS-Net", label, f"{args.short_steps} steps", lambda s, st=states[label]: network_features(st, s))
        main_state, seconds = _train(cfg("gsnet-q40", args.steps), resume=True)
        timings[f"GS-Net Q-Render K=40, steps {args.short_steps}->{args.steps}"] = seconds
        score("GS-Net", "Q-Render K=40", f"{args.steps} steps", lambda s: network_features(main_state, s))
        per_scene = {"GS-Net generalised": network_features(main_state, held)}
        overfit_state, timings[f"GS-Net overfit to the held-out room, {args.steps} steps"] = _train(
            cfg("gsnet-overfit-q40", args.steps, scenes=[held_path]))
        per_scene["GS-Net overfit"] = network_features(overfit_state, held)
        score("GS-Net overfit", "Q-Render K=40", f"{args.steps} steps", lambda s: per_scene["GS-Net overfit"],
              ("held-out",))
        watch = Stopwatch()
        per_scene["free features"] = fit_free_features(held, cfg("free-features", args.steps, scenes=[held_path]))
        timings[f"free features on the held-out room, {args.steps} steps"] = watch.seconds
        score("free features (no 3D term)", "Q-Render K=40", f"{args.steps} steps",
              lambda s: per_scene["free features"], ("held-out",))
        registration = register(held.gaussians, scene_views([held]), DRSPLAT_K, total=len(held.frames))
        per_scene["Dr.Splat registration"] = registration.features
        timings["Dr.Splat registration of the held-out room"] = registration.seconds
        score("Dr.Splat registration", f"top-{DRSPLAT_K} contributors", "no training",
              lambda s: registration.features, ("held-out",))
        images = []
        for split, scene in eval_scenes.items():
            cams = room_overview_cameras(scene.gaussians, *PANEL_SIZE)
            images += write_visuals(scene, network_features(main_state, scene), gts[split], out / "images" / "gsnet", cams)
            if split == "held-out":
                images += write_comparison(scene, {name: per_scene[name] for name in TABLE2_ROWS}, gts[split],
                                           out / "images" / "compared", cams)

    wall = wall_clock.seconds
    table = markdown_table(rows)
    short = {label: {r["split"]: r for r in rows if r["method"] == f"GS-Net / {label} / {args.short_steps} steps"}
             for _, _, label in COMPARED}
    held_rows = {name: next(r for r in rows if r["split"] == "held-out" and r["method"].startswith(prefix)
                            and not r["method"].endswith(f"/ {args.short_steps} steps"))
                 for name, prefix in zip(TABLE2_ROWS, ("GS-Net / Q-Render K=40", "Dr.Splat", "GS-Net overfit", "free"))}
    (out / "results.json").write_text(json.dumps({"rows": rows, "timings_s": timings, "wall_s": wall,
                                                  "mask_accuracy19": mask_accuracy, "args": vars(args),
                                                  "registration": registration.summary()},
                                                 indent=1, default=str))
    pngs = [p for p in images if p.suffix == ".png"]
    report = ["# qr-cl demo", "",
              f"GS-Net (small sparse UNet) trained on {len(train_paths)} synthetic rooms; evaluated on a held-out "
              f"room ({Path(held_path).name}) and a training room ({Path(train_paths[0]).name}). The \"CLIP\" "
              "features are simulated" + (" around the real CLIP ViT-B/32 text embeddings of the class names (a mask's "
              "feature names its own class among the 19 evaluated ones for "
              f"{100 * min(mask_accuracy):.0f}-{100 * max(mask_accuracy):.0f} % of the masks of these rooms; "
              "CLIP on object crops: about 60-75 %)" if args.features == "clip" else
              " from random, nearly orthogonal class prototypes") + "; see qr_cl/app/scenes/room_features.py. "
              f"mIoU/mAcc in % over the classes present, ground truth {truth_text}.", "",
              "## Table 2: GS-Net against the per-scene methods (held-out room, one seed)", "",
              f"GS-Net's runs take {args.steps} steps of {args.views} views x {args.rays} rays; one seed, so differences "
              "of a point or two are within run-to-run noise (`qr-cl reproduce` repeats them over three seeds and "
              "judges the paper's claims). " + ROWS_TEXT, "",
              *table2_lines({name: {c: Stat.of([100 * r["metrics"][int(c[-2:])][c[:4]]]) for c in COLUMNS}
                             for name, r in held_rows.items()}), "",
              f"Dr.Splat's registration (K={DRSPLAT_K}) reached {int(registration.reached.sum())} of "
              f"{len(held.gaussians)} Gaussians ({held_rows['Dr.Splat registration']['metrics'][19]['unlabelled']} "
              f"labelled ones keep no feature and count as unlabelled) in {registration.seconds:.1f} s. mIoU19 over "
              "only the Gaussians the room's views reach (Q-Render K=40 selections; a per-scene fit trains no other): "
              + "; ".join(f"{name} {100 * r['reached']['miou']:.1f}" for name, r in held_rows.items()) + ".", "",
              "## Every model", "", table, "",
              f"## Renderers compared ({args.short_steps} steps of {args.views} views x {args.rays} rays each)", "",
              "The same network, budget and seed through each renderer (the Q-Render K=40 run is the first "
              f"{args.short_steps} steps of the main run). One seed per run: differences of a point or two are "
              "within run-to-run noise (`qr-cl reproduce` measures it, with more renderers and the paper's numbers).",
              "", "| renderer | held-out mIoU19 | held-out mAcc19 | training-room mIoU19 | train s |",
              "| --- | ---: | ---: | ---: | ---: |"]
    report += [f"| {label} | {100 * r['held-out']['metrics'][19]['miou']:.1f} | "
               f"{100 * r['held-out']['metrics'][19]['macc']:.1f} | {100 * r['training']['metrics'][19]['miou']:.1f} | "
               f"{timings[f'GS-Net {label}, {args.short_steps} steps']:.0f} |" for label, r in short.items()]
    report += ["", "## Wall times", "", "| run | s |", "| --- | ---: |"]
    report += [f"| {k} | {v:.1f} |" for k, v in timings.items()] + [f"| whole demo | {wall:.1f} |", "", "## Images",
               "", "From above a corner of the room. images/gsnet: RGB | PCA of the Q-Render feature image | predicted "
               "classes | ground truth (labelled Gaussians only) | cosine of the feature image to one class's text "
               "feature (stretched). images/compared (held-out room): RGB | the predicted classes of GS-Net "
               "generalised, Dr.Splat's registration (white: Gaussians without a feature), GS-Net overfit and the free "
               "features | ground truth. Colours also in images/gsnet/legend.md.", ""]
    report += [f"![{p.stem}]({p.relative_to(out)})" for p in pngs]
    (out / "report.md").write_text("\n".join(report) + "\n")
    print(table)
    print(f"demo finished in {wall:.0f} s. Report: {(out / 'report.md').resolve()}")
    return 0
