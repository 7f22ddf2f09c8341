"""The rays a training step renders: pixels drawn inside masks, their selections (gathered from
whole-view selections kept in a :class:`~qr_cl.render.SelectionCache`) re-indexed into a compact
table of the Gaussians they use, and their loss (shared by GS-Net training and the free-feature fit).

A step touches only what its rays select: the Gaussians are frozen, so the selections of a step's
rays (geometry only) are made first (:func:`step_rays`), the features are computed for the union
of the Gaussians they use (a compact [U,C] table) and rendered through the selections re-indexed
into it (:func:`rays_loss`); the gradient flows back through those U rows only."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F

from ...render import (BackwardIndex, RasterPlan, Selection, SelectionCache, blend, compact_selections,
                       concat_selections, gather_rays, rasterize_plan, select_rays)
from ...scene import Camera, Gaussians
from ..scenes.folders import Frame, SceneData
from .loss import cosine_logits, head_cosine_logits


class RaySettings(Protocol):
    """What :func:`scene_loss` reads of a run's settings (a ``TrainConfig`` has them)."""

    views: int
    rays: int
    sampler: str
    k: int
    temperature: float


def sample_rays(frame: Frame, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` pixels drawn uniformly (with replacement) among those of ``frame`` inside a mask:
    pixels [n,2] int32 (x, y) and their mask rows [n] int64. Empty arrays if the frame has no mask."""
    ys, xs = np.nonzero(frame.masks >= 0)
    if len(xs) == 0:
        return np.zeros((0, 2), np.int32), np.zeros(0, np.int64)
    pick = rng.integers(0, len(xs), n)
    pixels = np.stack([xs[pick], ys[pick]], 1).astype(np.int32)
    return pixels, frame.masks[ys[pick], xs[pick]].astype(np.int64)


def camera_plan(gaussians: Gaussians, camera: Camera) -> RasterPlan:
    """Projection and tile lists of ``gaussians`` for ``camera``."""
    host = [np.ascontiguousarray(np.asarray(a), np.float32)
            for a in (gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities)]
    return rasterize_plan(*host, camera.viewmat, camera.K, camera.width, camera.height)


def view_plan(scene: SceneData, frame_index: int) -> RasterPlan:
    """Projection and tile lists of the scene's Gaussians for frame ``frame_index``'s camera."""
    return camera_plan(scene.gaussians, scene.frames[frame_index].camera)


def frame_selection(scene: SceneData, frame_index: int, pixels: np.ndarray, sampler: str, k: int,
                    cache: SelectionCache | None = None) -> Selection:
    """The selection of ``pixels`` [P,2] (x, y) of frame ``frame_index`` of ``scene``: gathered
    (:func:`qr_cl.render.gather_rays`: the same entries a selection of those
    pixels computes) from the view's whole-image selection, which ``cache`` keeps under (scene,
    view, sampler, K) once made, while it has room (:meth:`SelectionCache.get_if_room`); selected
    afresh when ``cache`` is None or full."""
    whole = None if cache is None else cache.get_if_room(
        (str(scene.root), frame_index, sampler, k), lambda: select_rays(view_plan(scene, frame_index), sampler, k))
    if whole is None:
        return select_rays(view_plan(scene, frame_index), sampler, k, pixels)
    return gather_rays(whole, pixels[:, 1].astype(np.int64) * whole.plan.width + pixels[:, 0])


@dataclass
class StepRays:
    """The rays of one scene that a training step renders, with their selections re-indexed into a
    compact feature table.

    ``rows`` [U] int64: the Gaussians any of the rays selects (ascending), the table's rows;
    ``selection``: the rays of all views, view after view, as one compact selection of U rows (one
    blend, one backward); per view ``targets`` [P] int64 (each ray's mask row) and
    ``mask_features`` [M,C] float32 (the view's unit mask features). ``n_gaussians`` is the
    scene's N. ``backward_index``: what the selection's blend backward reads of it, kept here (made ahead
    by :func:`qr_cl.render.prepare_backward` where a trainer does so).
    """

    rows: np.ndarray
    selection: Selection
    targets: list[np.ndarray]
    mask_features: list[np.ndarray]
    n_gaussians: int
    backward_index: BackwardIndex = field(default_factory=BackwardIndex)

    @property
    def n_rays(self) -> int:
        return sum(len(t) for t in self.targets)

    @property
    def touched(self) -> float:
        """Fraction of the scene's Gaussians the step's rays use (U / N)."""
        return len(self.rows) / max(self.n_gaussians, 1)


def step_rays(scene: SceneData, cfg: RaySettings, rng: np.random.Generator,
              cache: SelectionCache | None = None) -> StepRays:
    """Draw ``cfg.views`` random views of ``scene`` with two or more masks and ``cfg.rays`` rays
    inside masks per view, select them (gathered from ``cache``'s whole-image selections, or
    selected afresh when None) and re-index the selections into the Gaussians they use."""
    usable = [i for i, f in enumerate(scene.frames) if len(f.features) > 1]
    if not usable:
        raise ValueError(f"{scene.root}: no frame has two or more masks to contrast")
    picked = rng.choice(usable, cfg.views, replace=cfg.views > len(usable))
    selections, targets, masks = [], [], []
    for v in picked:
        frame = scene.frames[int(v)]
        pixels, target = sample_rays(frame, cfg.rays, rng)
        selections.append(frame_selection(scene, int(v), pixels, cfg.sampler, cfg.k, cache))
        targets.append(target)
        masks.append(frame.features)
    rows, (compact,) = compact_selections([concat_selections(selections)])
    return StepRays(rows, compact, targets, masks, len(scene.gaussians))


def rays_loss(rays: StepRays, table: torch.Tensor, temperature: float, head: torch.Tensor | None = None) -> torch.Tensor:
    """Mean over the step's views of the contrastive loss of its rays rendered from ``table``
    [U,C] (the rows of the Gaussians ``rays.rows``, in that order; gradients flow to it). With
    ``head`` [C',C] the rays are ``rendered @ head.T``, scored without being made
    (:func:`~qr_cl.app.training.loss.head_cosine_logits`): a table of
    :meth:`~qr_cl.backbone.GSNet.head_inputs` rows with its network's
    :meth:`~qr_cl.backbone.GSNet.head_matrix`."""
    if table.ndim != 2 or table.shape[0] != len(rays.rows):
        raise ValueError(f"table must be [{len(rays.rows)}, C] (one row per Gaussian in rays.rows), "
                         f"got {tuple(table.shape)}")
    rendered = blend(rays.selection, table, backward_index=rays.backward_index)
    sizes = [len(t) for t in rays.targets]
    masks = [torch.from_numpy(m) for m in rays.mask_features]
    logits = cosine_logits(rendered, sizes, masks, temperature) if head is None else \
        head_cosine_logits(rendered, head, sizes, masks, temperature)
    losses = [F.cross_entropy(view, torch.from_numpy(target)) for view, target in zip(logits, rays.targets)]
    return torch.stack(losses).mean()


def scene_loss(scene: SceneData, features: torch.Tensor, cfg: RaySettings, rng: np.random.Generator,
               cache: SelectionCache | None = None) -> tuple[torch.Tensor, int]:
    """Mean contrastive loss over ``cfg.views`` random views of ``cfg.rays`` rays rendered from
    ``features`` [N,C] (all Gaussians; only the rows the rays use are read); (loss, rays used)."""
    rays = step_rays(scene, cfg, rng, cache)
    return rays_loss(rays, features[torch.from_numpy(rays.rows)], cfg.temperature), rays.n_rays
