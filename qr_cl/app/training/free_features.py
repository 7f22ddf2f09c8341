"""Free features through the renderer, no 3D term: per-Gaussian features optimized on one scene.

No network: a learnable [N,C] table (rows L2-normalized before rendering, like GS-Net's output)
is fitted to one scene's masks with the same loss, sampler, views and rays per step as GS-Net.
Nothing ties a Gaussian to its neighbours: each ray's blend of its Gaussians matches its mask
while the Gaussians themselves may hold noise, and the Gaussians no ray selects keep their random
start. It is not a per-scene method from the literature (those add a 3D term, codebooks or a
registration: :mod:`qr_cl.app.registration` is Dr.Splat's); it shows what the renderer's loss alone
makes of free features.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from ...render import SelectionCache
from ..scenes.folders import SceneData
from .rays import RaySettings, rays_loss, step_rays


class BaselineSettings(RaySettings, Protocol):
    """What the fit reads of a run's settings (a ``TrainConfig`` has them)."""

    steps: int
    seed: int


def fit_free_features(scene: SceneData, cfg: BaselineSettings, lr: float = 0.05, progress: bool = True,
                      cache: SelectionCache | None = None) -> np.ndarray:
    """Optimize free features of ``scene`` for ``cfg.steps`` steps (Adam at ``lr``; views, rays,
    sampler, K and temperature from ``cfg``). Returns unit features [N,C] float32.

    A step renders from the rows its rays select (normalized there); their gradient is written
    into the table's persistent gradient (zero elsewhere) and a fused Adam updates the whole table
    in place, so no [N,C] array is allocated per step. ``cache`` keeps the views' whole-image
    selections (default: 1 GiB of them)."""
    gen = torch.Generator().manual_seed(cfg.seed)
    table = torch.nn.Parameter(torch.randn(len(scene.gaussians), scene.feature_dim, generator=gen))
    table.grad = torch.zeros_like(table)
    opt = torch.optim.Adam([table], lr=lr, fused=True)
    cache = SelectionCache(1 << 30) if cache is None else cache
    bar = tqdm(range(cfg.steps), desc=f"free features {scene.name}", unit="step", disable=not progress)
    for step in bar:
        rays = step_rays(scene, cfg, np.random.default_rng([cfg.seed, step, 0]), cache)
        rows = torch.from_numpy(rays.rows)
        used = table.detach().index_select(0, rows).requires_grad_()
        loss = rays_loss(rays, F.normalize(used, dim=1), cfg.temperature)
        loss.backward()
        table.grad.zero_()
        table.grad.index_copy_(0, rows, used.grad)
        opt.step()
        bar.set_postfix(loss=f"{loss.detach().item():.3f}")
    return F.normalize(table.detach(), dim=1).numpy()
