"""Study: GS-Net trained through each renderer of the plan with the same budget, and the per-scene
methods of Table 2 on the held-out room itself (GS-Net overfit to it, Dr.Splat's registration, free
features through the renderer), scored on the held-out room (mIoU/mAcc)."""
from __future__ import annotations

from dataclasses import asdict
from pathlib import Path

import numpy as np

from ..evaluation.metrics import SUBSETS
from ..evaluation.scoring import evaluate_features
from ..scenes.folders import SceneData, load_scene_folder
from ..timing import Stopwatch
from ..registration.register import register, scene_views
from ..training.free_features import fit_free_features
from ..training.config import TrainConfig
from ..training.network import network_features
from ..training.trainer import train
from .plan import NOISE_K, Plan, TrainingRun
from .rooms import noisy_scene


def metric_summary(metrics: dict, suffix: str = "") -> dict:
    """{"miou19", "macc19", ...} (names + ``suffix``) in % from
    :func:`qr_cl.app.evaluation.scoring.evaluate_features`' result."""
    return {f"{name}{s}{suffix}": 100 * metrics[s][name] for s in metrics for name in ("miou", "macc")}


def held_out_scores(held: SceneData, features: np.ndarray, gt: np.ndarray, reached: np.ndarray) -> dict:
    """mIoU/mAcc (19/15/10 classes) of per-Gaussian ``features`` [N,C] of the held-out room over
    all labelled Gaussians, and mIoU19/mAcc19 over those the room's views reach (``reached`` [N]
    bool; keys ``miou19_reached``, ``macc19_reached``)."""
    scores = metric_summary(evaluate_features(held, features, gt, tuple(SUBSETS)))
    return {**scores, **metric_summary(evaluate_features(held, features, np.where(reached, gt, -1), (19,)),
                                       "_reached")}


def train_and_evaluate(plan: Plan, run: TrainingRun, train_paths: list[Path], held: SceneData, gt: np.ndarray,
                       reached: np.ndarray, out: Path, seed: int, prefix: str = "") -> dict:
    """Train GS-Net through ``run``'s renderer with the plan's budget (on rooms with ``run.noise``
    opacity noise) and evaluate it on the held-out room (features predicted from the room with
    the same noise, scored against the clean room's ground truth; :func:`held_out_scores`). The
    run's folder is ``out``/runs/``prefix``<renderer>-seed<seed>."""
    scenes = [noisy_scene(p, run.noise, seed) if run.noise else p for p in train_paths]
    name = prefix + f"{run.sampler}{run.k}" + (f"-noise{run.noise:g}" if run.noise else "") + f"-seed{seed + run.seed}"
    cfg = TrainConfig(scenes=[str(p) for p in scenes], out=str(out / "runs" / name), steps=plan.steps,
                      views=plan.views, rays=plan.rays, sampler=run.sampler, k=run.k or NOISE_K,
                      seed=seed + run.seed, checkpoint_every=plan.steps)
    watch = Stopwatch()
    state = train(cfg).state()
    seconds = watch.seconds
    scene = load_scene_folder(noisy_scene(held.root, run.noise, seed)) if run.noise else held
    return {**asdict(run), "label": run.label, "steps": plan.steps, "train_seed": seed + run.seed, "train_s": seconds,
            "final_loss": state["history"][-1], "checkpoint": str(Path(cfg.out) / "checkpoint.pt"),
            **held_out_scores(held, network_features(state, scene), gt, reached)}


#: The label of the free-feature fit in tables.
FREE_FEATURES = f"free features through Q-Render K={NOISE_K} (no 3D term)"


def free_feature_scores(plan: Plan, held: SceneData, gt: np.ndarray, reached: np.ndarray, out: Path,
                        seed: int) -> tuple[dict, np.ndarray]:
    """Free features (:func:`qr_cl.app.training.free_features.fit_free_features`) fitted on the
    held-out room itself with GS-Net's budget through Q-Render K=40 and training seed ``seed``:
    (their scores, scored like the runs; the features [N,C])."""
    cfg = TrainConfig(scenes=[str(held.root)], out=str(out / "runs" / f"free-features-seed{seed}"), steps=plan.steps,
                      views=plan.views, rays=plan.rays, sampler="quantile", k=NOISE_K, seed=seed)
    watch = Stopwatch()
    features = fit_free_features(held, cfg)
    return ({"label": FREE_FEATURES, "steps": plan.steps, "train_seed": seed, "train_s": watch.seconds,
             **held_out_scores(held, features, gt, reached)}, features)


def overfit_scores(plan: Plan, held: SceneData, gt: np.ndarray, reached: np.ndarray, out: Path, seed: int) -> dict:
    """GS-Net overfit to the held-out room (the paper's overfit row): the same network and budget
    through Q-Render K=40, trained on the held-out room alone with seed ``seed``, scored like the
    runs."""
    name = f"overfit-quantile{NOISE_K}-seed{seed}"
    cfg = TrainConfig(scenes=[str(held.root)], out=str(out / "runs" / name), steps=plan.steps, views=plan.views,
                      rays=plan.rays, sampler="quantile", k=NOISE_K, seed=seed, checkpoint_every=plan.steps)
    watch = Stopwatch()
    state = train(cfg).state()
    return {"label": f"GS-Net overfit, Q-Render K={NOISE_K}", "steps": plan.steps, "train_seed": seed,
            "train_s": watch.seconds, "final_loss": state["history"][-1],
            "checkpoint": str(Path(cfg.out) / "checkpoint.pt"), **held_out_scores(held, network_features(state, held),
                                                                                  gt, reached)}


def registration_scores(plan: Plan, held: SceneData, gt: np.ndarray, reached: np.ndarray) -> tuple[dict, np.ndarray]:
    """Dr.Splat's registration (:func:`qr_cl.app.registration.register.register`, K =
    ``plan.drsplat_k``, the level GS-Net trains on) of the held-out room, scored like the runs:
    (the scores with the registration's summary and the labelled Gaussians it leaves without a
    feature, the features [N,C])."""
    result = register(held.gaussians, scene_views([held]), plan.drsplat_k, total=len(held.frames))
    labelled = gt >= 0
    return ({"label": f"Dr.Splat registration, top-{plan.drsplat_k} contributors", **result.summary(),
             "labelled_unreached": int((labelled & ~result.reached).sum()), "labelled": int(labelled.sum()),
             **held_out_scores(held, result.features, gt, reached)}, result.features)
