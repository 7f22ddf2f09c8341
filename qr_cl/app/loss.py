"""The contrastive distillation loss of the paper (Sec. 4.3, Eq. 2), ray sampling inside masks,
and the loss of a scene rendered through a sampler (shared by GS-Net training and the baseline).

A step touches only what its rays select: the Gaussians are frozen, so the selections of a step's
rays (geometry only) are made first (:func:`step_rays`), the features are computed for the union
of the Gaussians they use (a compact [U,C] table) and rendered through the selections re-indexed
into it (:func:`rays_loss`); the gradient flows back through those U rows only."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch
import torch.nn.functional as F

from ..render import blend, rasterize_plan
from ..stages.binning import RasterPlan
from ..stages.select import (CompactSelection, Selection, compact_selections, concat_selections, gather_rays,
                              select)
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


def view_plan(scene: SceneData, frame_index: int) -> RasterPlan:
    """Projection and tile lists of the scene's Gaussians for frame ``frame_index``'s camera."""
    g, cam = scene.gaussians, scene.frames[frame_index].camera
    host = [np.ascontiguousarray(np.asarray(a), np.float32) for a in (g.means, g.quats, g.scales, g.opacities)]
    return rasterize_plan(*host, cam.viewmat, cam.K, cam.width, cam.height)


class ViewSelections:
    """Whole-image selections of training views, each computed once (geometry, camera, sampler
    and K only) and kept while they fit in ``max_bytes`` of device memory; a step's rays are then
    gathered from them (:func:`qr_cl.stages.select.gather_rays`: the same entries a per-step
    :func:`qr_cl.stages.select.select` of those pixels computes). Views that no longer fit are
    selected ray by ray every step (nothing kept is evicted, so nothing is computed twice).
    ``max_bytes`` = 0 keeps none."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = int(max_bytes)
        self.nbytes = 0
        self._views: dict[tuple, Selection] = {}
        self._last_size = 0

    def select(self, scene: SceneData, frame_index: int, pixels: np.ndarray, sampler: str, k: int) -> Selection:
        """The selection of ``pixels`` [P,2] (x, y) of frame ``frame_index`` of ``scene``."""
        key = (str(scene.root), frame_index, sampler, k)
        whole = self._views.get(key)
        if whole is None and self.nbytes + self._last_size <= self.max_bytes:
            plan = view_plan(scene, frame_index)
            whole = select(plan, sampler, k)
            self._last_size = whole.nbytes + plan.nbytes
            if self.nbytes + self._last_size <= self.max_bytes:
                self._views[key] = whole
                self.nbytes += self._last_size
        if whole is None:
            return select(view_plan(scene, frame_index), sampler, k, pixels)
        return gather_rays(whole, pixels[:, 1].astype(np.int64) * whole.plan.width + pixels[:, 0])


@dataclass
class StepRays:
    """The rays of one scene that a training step renders, with their selections re-indexed into a
    compact feature table.

    ``rows`` [U] int64: the Gaussians any of the rays selects (ascending), the table's rows;
    ``selection``: the rays of all views, view after view, as one CompactSelection of U rows (one
    blend, one backward); per view ``targets`` [P] int64 (each ray's mask row) and
    ``mask_features`` [M,C] float32 (the view's unit mask features). ``n_gaussians`` is the
    scene's N.
    """

    rows: np.ndarray
    selection: CompactSelection
    targets: list[np.ndarray]
    mask_features: list[np.ndarray]
    n_gaussians: int

    @property
    def n_rays(self) -> int:
        return sum(len(t) for t in self.targets)

    @property
    def touched(self) -> float:
        """Fraction of the scene's Gaussians the step's rays use (U / N)."""
        return len(self.rows) / max(self.n_gaussians, 1)


def step_rays(scene: SceneData, cfg: RaySettings, rng: np.random.Generator,
              views: ViewSelections | None = None) -> StepRays:
    """Draw ``cfg.views`` random views of ``scene`` with two or more masks and ``cfg.rays`` rays
    inside masks per view, select them (gathered from ``views``' whole-image selections, or
    selected afresh when None) and re-index the selections into the Gaussians they use."""
    usable = [i for i, f in enumerate(scene.frames) if len(f.features) > 1]
    if not usable:
        raise ValueError(f"{scene.root}: no frame has two or more masks to contrast")
    picked = rng.choice(usable, cfg.views, replace=cfg.views > len(usable))
    selections, targets, masks = [], [], []
    for v in picked:
        frame = scene.frames[int(v)]
        pixels, target = sample_rays(frame, cfg.rays, rng)
        if views is None:
            selections.append(select(view_plan(scene, int(v)), cfg.sampler, cfg.k, pixels))
        else:
            selections.append(views.select(scene, int(v), pixels, cfg.sampler, cfg.k))
        targets.append(target)
        masks.append(frame.features)
    rows, (compact,) = compact_selections([concat_selections(selections)])
    return StepRays(rows, compact, targets, masks, len(scene.gaussians))


def rays_loss(rays: StepRays, table: torch.Tensor, temperature: float) -> torch.Tensor:
    """Mean over the step's views of the contrastive loss of its rays rendered from ``table``
    [U,C] (the features of the Gaussians ``rays.rows``, in that order; gradients flow to it)."""
    if table.ndim != 2 or table.shape[0] != len(rays.rows):
        raise ValueError(f"table must be [{len(rays.rows)}, C] (one row per Gaussian in rays.rows), "
                         f"got {tuple(table.shape)}")
    images = torch.split(blend(rays.selection, table), [len(t) for t in rays.targets])
    losses = [contrastive_loss(image, torch.from_numpy(target), torch.from_numpy(masks), temperature)
              for image, target, masks in zip(images, rays.targets, rays.mask_features)]
    return torch.stack(losses).mean()


def scene_loss(scene: SceneData, features: torch.Tensor, cfg: RaySettings, rng: np.random.Generator,
               views: ViewSelections | None = None) -> tuple[torch.Tensor, int]:
    """Mean contrastive loss over ``cfg.views`` random views of ``cfg.rays`` rays rendered from
    ``features`` [N,C] (all Gaussians; only the rows the rays use are read); (loss, rays used)."""
    rays = step_rays(scene, cfg, rng, views)
    return rays_loss(rays, features[torch.from_numpy(rays.rows)], cfg.temperature), rays.n_rays
