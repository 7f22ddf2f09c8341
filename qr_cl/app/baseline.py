"""The per-scene "memory-based" baseline: free per-Gaussian features optimized through the renderer.

No network: a learnable [N,C] table (rows L2-normalized before rendering, like GS-Net's output)
is fitted to one scene's masks with the same loss, sampler, views and rays per step as GS-Net.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from .data import SceneData
from .loss import RaySettings, scene_loss


class BaselineSettings(RaySettings, Protocol):
    """What the baseline reads of a run's settings (a ``TrainConfig`` has them)."""

    steps: int
    seed: int


def fit_free_features(scene: SceneData, cfg: BaselineSettings, lr: float = 0.05, progress: bool = True) -> np.ndarray:
    """Optimize free features of ``scene`` for ``cfg.steps`` steps (Adam at ``lr``; views, rays,
    sampler, K and temperature from ``cfg``). Returns unit features [N,C] float32."""
    gen = torch.Generator().manual_seed(cfg.seed)
    table = torch.nn.Parameter(torch.randn(len(scene.gaussians), scene.feature_dim, generator=gen))
    opt = torch.optim.Adam([table], lr=lr)
    bar = tqdm(range(cfg.steps), desc=f"baseline {scene.name}", unit="step", disable=not progress)
    for step in bar:
        opt.zero_grad()
        loss, _ = scene_loss(scene, F.normalize(table, dim=1), cfg, np.random.default_rng([cfg.seed, step, 0]))
        loss.backward()
        opt.step()
        bar.set_postfix(loss=f"{loss.detach().item():.3f}")
    return F.normalize(table.detach(), dim=1).numpy()
