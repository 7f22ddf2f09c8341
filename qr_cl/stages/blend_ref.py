"""Twins of blend.cl (:mod:`qr_cl.stages.blend`), in float64: :func:`blend` (numpy) of a Selection,
:func:`render_rays` (torch, differentiable in the splats) of its geometry backward."""
from __future__ import annotations

import numpy as np
import torch

from ..runtime import ALPHA_MAX


def blend(ids: np.ndarray, weights: np.ndarray, features: np.ndarray, t_rem: np.ndarray | None = None,
          background=None) -> np.ndarray:
    """image [P,C] = sum_j weights[p,j] features[ids[p,j]] (+ t_rem[p] background), in float64.
    ids [P,L] (-1 = padding), weights [P,L], features [N,C]."""
    f = np.asarray(features, np.float64)
    gathered = f[np.maximum(ids, 0)] * np.where(ids >= 0, weights, 0)[..., None]
    image = gathered.sum(1) if ids.shape[1] else np.zeros((len(ids), f.shape[1]))
    if background is not None:
        image = image + np.asarray(t_rem, np.float64)[:, None] * np.asarray(background, np.float64)[None]
    return image


def render_rays(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
                ids: np.ndarray, pixels: np.ndarray, normalized: bool,
                background: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The blend of fixed per-ray Gaussian lists as a differentiable torch function of the splats
    (the reference of blend.cl's geometry backward): ids [P,L] (depth order, -1 = padding), pixels
    [P,2] integer (x, y); means2d [N,2] px, conics [N,3] (A, B, C), opacities [N], features [N,C].

    alpha = min(ALPHA_MAX, opacity exp(-sigma)) at the pixel centre, w_j = T_j alpha_j
    (T_j = prod_{i<j} (1 - alpha_i)); ``normalized`` (the K samplers): w_j / sum_i w_i, with the
    background only where a ray has no entry. Returns image [P,C] and the final T [P] (1 - alpha).
    """
    valid = torch.as_tensor(ids >= 0)
    g = torch.as_tensor(np.maximum(ids, 0), dtype=torch.long)
    centre = torch.as_tensor(np.asarray(pixels, np.float64) + 0.5, dtype=means2d.dtype)
    d = means2d[g] - centre[:, None]
    A, B, C = conics[g].unbind(-1)
    sigma = 0.5 * (A * d[..., 0] ** 2 + C * d[..., 1] ** 2) + B * d[..., 0] * d[..., 1]
    alpha = torch.where(valid, torch.clamp(opacities[g] * torch.exp(-sigma), max=ALPHA_MAX), 0.0)
    T = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha], 1), 1)
    w = T[:, :-1] * alpha
    t_final = T[:, -1]
    if normalized:
        w = w / w.sum(1, keepdim=True).clamp_min(torch.finfo(w.dtype).tiny)
        t_rem = (~valid.any(1)).to(w.dtype)
    else:
        t_rem = t_final
    image = (w[..., None] * features[g]).sum(1)
    if background is not None:
        image = image + t_rem[:, None] * background
    return image, t_final
