"""Twins of blend.cl (:mod:`qr_cl.stages.blend`), in float64: :func:`blend` (numpy) of a Selection,
:func:`render_rays` (torch, differentiable in the splats) of its geometry backward. Both take a
feature table whole (``row0`` 0) or a row part of it, its rows [row0, row0 + R): entries of other
Gaussians then blend nothing (their alphas still count in the transmittances)."""
from __future__ import annotations

import numpy as np
import torch

from ..runtime import ALPHA_MAX


def part_rows(ids: np.ndarray, row0: int, n_rows: int) -> np.ndarray:
    """The row of each entry's feature in a table part of the rows [row0, row0 + n_rows): id - row0,
    or n_rows (one past the part: a zero row) for padding and the ids of other parts."""
    local = np.asarray(ids, np.int64) - row0
    return np.where((np.asarray(ids) >= 0) & (local >= 0) & (local < n_rows), local, n_rows)


def blend(ids: np.ndarray, weights: np.ndarray, features: np.ndarray, t_rem: np.ndarray | None = None,
          background=None, row0: int = 0) -> np.ndarray:
    """image [P,C] = sum_j weights[p,j] features[ids[p,j] - row0] (+ t_rem[p] background), in
    float64, over the entries whose id is in [row0, row0 + R). ids [P,L] (-1 = padding), weights
    [P,L], features [R,C] (rows [row0, row0 + R) of the table)."""
    f = np.asarray(features, np.float64)
    rows = np.concatenate([f, np.zeros((1, f.shape[1]))])[part_rows(ids, row0, len(f))]   # the last: zeros
    gathered = rows * np.asarray(weights, np.float64)[..., None]
    image = gathered.sum(1) if ids.shape[1] else np.zeros((len(ids), f.shape[1]))
    if background is not None:
        image = image + np.asarray(t_rem, np.float64)[:, None] * np.asarray(background, np.float64)[None]
    return image


def render_rays(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, features: torch.Tensor,
                ids: np.ndarray, pixels: np.ndarray, normalized: bool,
                background: torch.Tensor | None = None, row0: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """The blend of fixed per-ray Gaussian lists as a differentiable torch function of the splats
    (the reference of blend.cl's geometry backward): ids [P,L] (depth order, -1 = padding), pixels
    [P,2] integer (x, y); means2d [N,2] px (or [P,L,2], each entry's own copy: its gradient is then
    the per-pixel dL/dmean2d that gsplat's absgrad sums in absolute value), conics [N,3] (A, B, C),
    opacities [N], features [R,C]: the rows [row0, row0 + R) of the table (entries of other
    Gaussians blend no feature, as in a row part of blend.cl).

    alpha = min(ALPHA_MAX, opacity exp(-sigma)) at the pixel centre, w_j = T_j alpha_j
    (T_j = prod_{i<j} (1 - alpha_i)); ``normalized`` (the K samplers): w_j / sum_i w_i, with the
    background only where a ray has no entry. Returns image [P,C] and the final T [P] (1 - alpha).
    """
    valid = torch.as_tensor(ids >= 0)
    g = torch.as_tensor(np.maximum(ids, 0), dtype=torch.long)
    centre = torch.as_tensor(np.asarray(pixels, np.float64) + 0.5, dtype=means2d.dtype)
    d = (means2d if means2d.ndim == 3 else means2d[g]) - centre[:, None]
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
    rows = torch.cat([features, features.new_zeros(1, features.shape[1])])[
        torch.as_tensor(part_rows(ids, row0, len(features)), dtype=torch.long)]
    image = (w[..., None] * rows).sum(1)
    if background is not None:
        image = image + t_rem[:, None] * background
    return image, t_final


def alpha_grads(alphas: np.ndarray, g: np.ndarray, normalized: bool, d_trem: np.ndarray | None = None) -> np.ndarray:
    """dL/dalpha [P,L] of the selected entries, the derivation blend.cl's ``blend_backward_alpha``
    implements, in float64. alphas [P,L] in depth order (0 for padding; padding's results are
    meaningless), g [P,L] = dImage[p] . F[id] (dL/dw of each entry), d_trem [P] = dL/dT_final
    (volume only).

    With T_j = prod_{i<j} (1 - a_i) and u_j = T_j a_j, du_i/da_j = T_j for i = j,
    -u_i / (1 - a_j) for i > j, and 0 for i < j; dT_final/da_j = -T_final / (1 - a_j). So
      volume (w = u):  dL/da_j = T_j g_j - (sum_{i>j} g_i u_i + d_trem T_final) / (1 - a_j);
      K samplers (w = u / U, U = sum_i u_i, the selection held fixed): dL/du_j = h_j =
      (g_j - sum_i g_i w_i) / U, and dL/da_j = T_j h_j - (sum_{i>j} h_i u_i) / (1 - a_j).
    """
    a = np.asarray(alphas, np.float64)
    T = np.cumprod(np.concatenate([np.ones((len(a), 1)), 1 - a], 1), 1)
    u = T[:, :-1] * a
    if normalized:
        U = u.sum(1, keepdims=True)
        w = np.divide(u, U, out=np.zeros_like(u), where=U > 0)
        h = np.divide(g - (g * w).sum(1, keepdims=True), U, out=np.zeros_like(u), where=U > 0)
        tail = np.zeros(len(a))
    else:
        h = np.asarray(g, np.float64)
        tail = np.zeros(len(a)) if d_trem is None else np.asarray(d_trem, np.float64) * T[:, -1]
    after = np.cumsum((h * u)[:, ::-1], 1)[:, ::-1] - h * u + tail[:, None]    # sum_{i>j} h_i u_i + tail
    return T[:, :-1] * h - after / (1 - a)
