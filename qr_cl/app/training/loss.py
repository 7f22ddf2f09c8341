"""The contrastive distillation loss of the paper (Sec. 4.3, Eq. 2): rendered ray features scored
against the unit features of their view's masks."""
from __future__ import annotations

import torch
import torch.nn.functional as F

from ...runtime import host_empty


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
    _check_views(sizes, rendered.shape[0], len(mask_features))
    return _CosineLogits.apply(rendered, float(temperature), tuple(int(n) for n in sizes), *mask_features)


def head_cosine_logits(sums: torch.Tensor, head: torch.Tensor, sizes: list[int], mask_features: list[torch.Tensor],
                       temperature: float) -> tuple[torch.Tensor, ...]:
    """:func:`cosine_logits` of the rays ``sums @ head.T`` without making them: ``sums`` [P,D]
    (e.g. rendered :meth:`~qr_cl.backbone.GSNet.head_inputs` rows, D + 1 channels there) and
    ``head`` [C,D] (:meth:`~qr_cl.backbone.GSNet.head_matrix`). A ray's similarity to a mask m is
    ``sums . (head.T m)`` over its norm ``|R sums|`` (head = QR with Q's columns orthonormal, R
    [min(C, D), D]; a norm under 1e-12 taken as 1e-12, as F.normalize does), so the cost is
    O(P D (M + D)) instead of O(P C (D + M)): the [P,C] rays are never formed."""
    _check_views(sizes, sums.shape[0], len(mask_features))
    if head.ndim != 2 or head.shape[1] != sums.shape[1]:
        raise ValueError(f"head {tuple(head.shape)} must be [C, {sums.shape[1]}] for sums {tuple(sums.shape)}")
    r = torch.linalg.qr(head).R
    inv = torch.linalg.vector_norm(sums @ r.T, dim=1, keepdim=True).clamp_min(1e-12).reciprocal()
    return tuple(s @ (m @ head).T * i / temperature
                 for s, i, m in zip(sums.split(sizes), inv.split(sizes), mask_features))


def _check_views(sizes: list[int], rays: int, views: int) -> None:
    """ValueError unless ``sizes`` split ``rays`` rays among ``views`` views."""
    if sum(sizes) != rays or len(sizes) != views:
        raise ValueError(f"sizes {list(sizes)} must split the {rays} rays among {views} views")


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
