"""How much training the quick plan needs: held-out per-class IoU of GS-Net (Q-Render K=40) against
the number of training rooms and steps, the probe that chose ``qr-cl reproduce --quick``'s budget.

One probe trains GS-Net on the first ``ROOMS`` "3dgs" rooms of the reproduction (seeds 0..ROOMS-1,
60k Gaussians; ``overfit``: the held-out room itself) and scores it on the held-out room (seed
1000) at each checkpoint of ``STEPS`` (training continues exactly from the last, as ``--resume``
does), printing one JSON line per checkpoint (mIoU19, per-class IoU, final loss, seconds) and the
classes' shares of the labelled Gaussians::

    python bench/quick_budget.py 4 150,300,600 > r4.log          # 4 rooms
    python bench/quick_budget.py overfit 150,300 > overfit.log    # the held-out room alone
    python bench/quick_budget.py --table r4.log overfit.log --out report.md

``--grid``, ``--sampler``/``-k`` and ``--seed`` change the network's voxels, the renderer and the seed.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from benchutil import print_table


def probe(rooms: str, checkpoints: list[int], out: Path, seed: int, sampler: str, k: int, grid: float) -> None:
    """Train and score at each checkpoint (module docstring), printing JSON lines."""
    from qr_cl.app.process import cap_kernel_threads, torch_threads
    cap_kernel_threads()
    from qr_cl.app.evaluation.labels import ground_truth
    from qr_cl.app.evaluation.metrics import NYU40_NAMES
    from qr_cl.app.evaluation.scoring import evaluate_features
    from qr_cl.app.scenes.folders import load_scene_folder
    from qr_cl.app.scenes.room_config import SyntheticConfig
    from qr_cl.app.scenes.synthetic import room_folder
    from qr_cl.app.training.config import TrainConfig
    from qr_cl.app.training.network import network_features
    from qr_cl.app.training.trainer import train

    def room(s: int) -> Path:
        return room_folder(SyntheticConfig(seed=s, n_gaussians=60000, style="3dgs", features="clip"))
    held = load_scene_folder(room(1000))
    paths = [str(held.root)] if rooms == "overfit" else [str(room(s)) for s in range(int(rooms))]
    gt, _ = ground_truth(held)
    for steps in checkpoints:
        watch = time.perf_counter()
        cfg = TrainConfig(scenes=paths, out=str(out), steps=steps, sampler=sampler, k=k, seed=seed,
                          checkpoint_every=steps, grid_size=grid)
        with torch_threads(1):
            state = train(cfg, resume=True, progress=False).state()
            metrics = evaluate_features(held, network_features(state, held), gt)[19]
        print(json.dumps({"rooms": rooms, "steps": steps, "s": round(time.perf_counter() - watch),
                          "miou19": round(100 * metrics["miou"], 1), "loss": round(state["history"][-1], 3),
                          "per_class": {NYU40_NAMES[c]: round(100 * v["iou"], 1)
                                        for c, v in metrics["per_class"].items()}}), flush=True)
    labelled = gt[gt >= 0]
    print(json.dumps({"share": {NYU40_NAMES[int(c)]: float((labelled == c).mean()) for c in np.unique(labelled)}}))


def table(logs: list[Path]) -> str:
    """The probes' JSON lines as one markdown table (classes above 1 % of the labelled Gaussians)."""
    rows, share = [], {}
    for log in logs:
        for line in log.read_text().splitlines():
            if line.startswith("{"):
                entry = json.loads(line)
                share.update(entry.get("share", {}))
                if "steps" in entry:
                    rows.append({"log": log.stem, **entry})
    classes = [c for c, v in sorted(share.items(), key=lambda p: -p[1]) if v > 0.01]
    lines = ["| probe | rooms | steps | mIoU19 | " + " | ".join(f"{c} ({100 * share[c]:.1f} %)" for c in classes) +
             " | final loss | s |", "| --- | --- |" + " ---: |" * (len(classes) + 4)]
    lines += [f"| {r['log']} | {r.get('rooms', '-')} | {r['steps']} | {r['miou19']:.1f} | " +
              " | ".join(f"{r['per_class'].get(c, float('nan')):.1f}" for c in classes) +
              f" | {r['loss']:.3f} | {r['s']} |" for r in rows]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rooms", nargs="?", help="training rooms (a number) or 'overfit'")
    parser.add_argument("steps", nargs="?", help="checkpoints, comma separated (e.g. 150,300,600)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sampler", default="quantile")
    parser.add_argument("-k", type=int, default=40)
    parser.add_argument("--grid", type=float, default=0.1, help="voxel size, m (default 0.1)")
    parser.add_argument("--runs", type=Path, default=Path("quick-budget-runs"), help="checkpoint folder root")
    parser.add_argument("--table", type=Path, nargs="+", help="turn these logs into a markdown table")
    parser.add_argument("--out", type=Path, help="with --table: write it to this file")
    args = parser.parse_args()
    if args.table:
        print_table(table(args.table), args.out)
        return
    if not (args.rooms and args.steps):
        parser.error("give ROOMS and STEPS (or --table LOGS)")
    name = f"{args.rooms}-{args.sampler}{args.k}-grid{args.grid:g}-seed{args.seed}"
    probe(args.rooms, [int(s) for s in args.steps.split(",")], args.runs / name, args.seed, args.sampler, args.k,
          args.grid)


if __name__ == "__main__":
    main()
