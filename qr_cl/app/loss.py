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
from ..runtime import host_empty
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
    (logits,) = cosine_logits(rendered, [rendered.shape[0]], [mask_features], temperature)
    return F.cross_entropy(logits, target)


def cosine_logits(rendered: torch.Tensor, sizes: list[int], mask_features: list[torch.Tensor],
                  temperature: float) -> tuple[torch.Tensor, ...]:
    """Logits of several views' rays at once: ``rendered`` [P,C] holds the views' rays one view
    after the other (``sizes`` [V] rays per view, summing to P); view v's rays are scored against
    its ``mask_features[v]`` [M_v,C]. Returns per view [P_v, M_v] = cos(ray, mask) / temperature,
    i.e. ``F.normalize(rendered_v, dim=1) @ mask_features[v].T / temperature``. The backward
    writes d rendered [P,C] into one pooled host array and allocates no other [P,C] array."""
    if sum(sizes) != rendered.shape[0] or len(sizes) != len(mask_features):
        raise ValueError(f"sizes {list(sizes)} must split the {rendered.shape[0]} rays among "
                         f"{len(mask_features)} views")
    return _CosineLogits.apply(rendered, float(temperature), tuple(int(n) for n in sizes), *mask_features)


class _CosineLogits(torch.autograd.Function):
    """:func:`cosine_logits`: logits_v = (r_v @ M_v^T) * inv_v / T with inv = 1 / max(|r|, 1e-12)
    (F.normalize's clamp); d r_v = s_v @ M_v - (sum_m s_v * (r_v @ M_v^T)) inv_v^2 r_v with
    s_v = g_v inv_v / T (no second term where the norm was clamped)."""

    @staticmethod
    def forward(ctx, rendered: torch.Tensor, temperature: float, sizes: tuple[int, ...], *masks: torch.Tensor):
        rendered = rendered.contiguous()
        norm = torch.linalg.vector_norm(rendered, dim=1, keepdim=True)
        inv = norm.clamp_min(1e-12).reciprocal_()
        sims = [r @ m.T for r, m in zip(torch.split(rendered, sizes), masks)]
        ctx.save_for_backward(rendered, inv, (norm > 1e-12).to(rendered.dtype), *sims, *masks)
        ctx.temperature, ctx.sizes = temperature, sizes
        return tuple(sim * i / temperature for sim, i in zip(sims, torch.split(inv, sizes)))

    @staticmethod
    def backward(ctx, *grads: torch.Tensor):
        rendered, inv, unclamped, *rest = ctx.saved_tensors
        n = len(ctx.sizes)
        sims, masks = rest[:n], rest[n:]
        d = torch.from_numpy(host_empty(tuple(rendered.shape))) if rendered.dtype == torch.float32 else \
            torch.empty_like(rendered)
        for g, sim, m, r, i, u, out in zip(grads, sims, masks, *(torch.split(t, ctx.sizes) for t in
                                                                (rendered, inv, unclamped, d))):
            if g is None:
                out.zero_()
                continue
            scaled = g * i / ctx.temperature
            torch.mm(scaled, m, out=out)
            out.addcmul_(r, (scaled * sim).sum(1, keepdim=True) * i * i * u, value=-1)
        return (d, None, None) + (None,) * n


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
    logits = cosine_logits(blend(rays.selection, table), [len(t) for t in rays.targets],
                           [torch.from_numpy(m) for m in rays.mask_features], temperature)
    losses = [F.cross_entropy(view, torch.from_numpy(target)) for view, target in zip(logits, rays.targets)]
    return torch.stack(losses).mean()


def scene_loss(scene: SceneData, features: torch.Tensor, cfg: RaySettings, rng: np.random.Generator,
               views: ViewSelections | None = None) -> tuple[torch.Tensor, int]:
    """Mean contrastive loss over ``cfg.views`` random views of ``cfg.rays`` rays rendered from
    ``features`` [N,C] (all Gaussians; only the rows the rays use are read); (loss, rays used)."""
    rays = step_rays(scene, cfg, rng, views)
    return rays_loss(rays, features[torch.from_numpy(rays.rows)], cfg.temperature), rays.n_rays
