"""The contrastive distillation loss of the paper (Sec. 4.3, Eq. 2), ray sampling inside masks,
and the loss of a scene rendered through a sampler (shared by GS-Net training and the baseline)."""
from __future__ import annotations

from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F

from ..render import rasterize
from .data import Frame, SceneData


class RaySettings(Protocol):
    """What :func:`scene_loss` reads of a run's settings (a ``TrainConfig`` has them)."""

    views: int
    rays: int
    sampler: str
    k: int
    temperature: float


def contrastive_loss(rendered: torch.Tensor, target: torch.Tensor, mask_features: torch.Tensor,
                     temperature: float = 0.1) -> torch.Tensor:
    """Mean over rays of -log softmax_j(sim(f_ray, f_j) / temperature)[target].

    rendered [P,C] rendered ray features (any norm; cosine similarity normalizes them),
    target [P] int64 row of each ray's own mask in ``mask_features`` (the positive),
    mask_features [M,C] unit features of all masks of the view (the others are the negatives).
    Eq. 2 with the positive kept in the denominator (InfoNCE / cross-entropy form).
    """
    if rendered.ndim != 2 or mask_features.ndim != 2 or rendered.shape[1] != mask_features.shape[1]:
        raise ValueError(f"rendered {tuple(rendered.shape)} and mask_features {tuple(mask_features.shape)} "
                         "must be [P,C] and [M,C]")
    logits = F.normalize(rendered, dim=1) @ mask_features.T / temperature
    return F.cross_entropy(logits, target)


def sample_rays(frame: Frame, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` pixels drawn uniformly (with replacement) among those of ``frame`` inside a mask:
    pixels [n,2] int32 (x, y) and their mask rows [n] int64. Empty arrays if the frame has no mask."""
    ys, xs = np.nonzero(frame.masks >= 0)
    if len(xs) == 0:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.int64)
    pick = rng.integers(0, len(xs), n)
    pixels = np.stack([xs[pick], ys[pick]], 1).astype(np.int32)
    return pixels, frame.masks[ys[pick], xs[pick]].astype(np.int64)


def render_rays(scene: SceneData, features: torch.Tensor, frame_index: int, pixels: np.ndarray,
                sampler: str, k: int) -> torch.Tensor:
    """Differentiable render of ``pixels`` [P,2] (x, y) of frame ``frame_index``: [P,C]."""
    g, cam = scene.gaussians, scene.frames[frame_index].camera
    out, _, _ = rasterize(g.means, g.quats, g.scales, g.opacities, features, cam.viewmat, cam.K,
                          cam.width, cam.height, sampler=sampler, k=k, pixels=pixels)
    return out


def scene_loss(scene: SceneData, features: torch.Tensor, cfg: RaySettings, rng: np.random.Generator) -> tuple[torch.Tensor, int]:
    """Mean contrastive loss over ``cfg.views`` random views of ``cfg.rays`` rays; (loss, rays used)."""
    usable = [i for i, f in enumerate(scene.frames) if len(f.features) > 1]
    if not usable:
        raise ValueError(f"{scene.root}: no frame has two or more masks to contrast")
    views = rng.choice(usable, cfg.views, replace=cfg.views > len(usable))
    losses, n = [], 0
    for v in views:
        frame = scene.frames[int(v)]
        pixels, target = sample_rays(frame, cfg.rays, rng)
        rendered = render_rays(scene, features, int(v), pixels, cfg.sampler, cfg.k)
        losses.append(contrastive_loss(rendered, torch.from_numpy(target), torch.from_numpy(frame.features),
                                       cfg.temperature))
        n += len(pixels)
    return torch.stack(losses).mean(), n
