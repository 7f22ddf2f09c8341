"""Study: top-K against Q-Render at small K on rooms given the depth structure that makes top-K fail
in the paper.

The plan's rooms measure as lacking it (:mod:`.ray_depth`: a ray's K largest weights reach as deep
as the quantile picks). ``plan.depth_room`` gives rooms that have it: surfaces as thick
semi-transparent shells of many faint layers, so a ray's weight decays through each surface and
its K largest weights lie in front of weight they never see (top-K's unseen share above
Q-Render's, as on the dense procedural room). GS-Net is trained on such rooms through top-K and
Q-Render at ``plan.depth_k``, with the plan's budget and seeds, and scored on a held-out room of
the same kind; the held-out room's ray depths are measured as the other scenes' are.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ..evaluation.labels import ground_truth, reached_gaussians
from ..scenes.folders import load_scene_folder
from .plan import NOISE_K, Plan, TrainingRun
from .ray_depth import ROOM, ray_depth_statistics
from .rooms import splat_rooms
from .training_runs import train_and_evaluate

#: The prefix of these runs' folders (beside the plan's own runs).
PREFIX = "depth-rooms-"


def depth_room_study(plan: Plan, seed: int, cache: Path | None, features: str, out: Path) -> dict | None:
    """The study (module docstring), or None when the plan has no ``depth_room``: {"room" (the
    overrides), "scenes", "runs" (as the plan's runs), "ray_depth" (the held-out room's row)}."""
    if not plan.depth_room:
        return None
    train_paths, held_path = splat_rooms(plan, seed, cache, features, plan.depth_room)
    held = load_scene_folder(held_path)
    gt, _ = ground_truth(held)
    reached = reached_gaussians(held, "quantile", NOISE_K)
    runs = [TrainingRun(sampler, plan.depth_k, 0.0, s) for s in range(plan.seeds) for sampler in ("topk", "quantile")]
    rows = [train_and_evaluate(plan, run, train_paths, held, gt, reached, out, seed, PREFIX)
            for run in tqdm(runs, desc="depth rooms", unit="run")]
    depth = ray_depth_statistics(held.name, ROOM, held.gaussians, [f.camera for f in held.frames[:plan.stats_views]],
                                 plan.depth_k, np.random.default_rng(seed), held.gaussian_labels)
    return {"room": plan.depth_room, "scenes": {"train": [p.name for p in train_paths], "held_out": held.name},
            "runs": rows, "ray_depth": depth}
