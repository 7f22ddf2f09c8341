"""The contrastive distillation loss of the paper (Sec. 4.3, Eq. 2) and ray sampling inside masks."""
from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from .data import Frame


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
