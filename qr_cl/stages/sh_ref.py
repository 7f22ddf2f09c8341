"""Twin of sh.cl (:mod:`qr_cl.stages.sh`), in torch: float64 for numpy inputs, differentiable
w.r.t. means and coefficients for tensor inputs (gsplat's SH convention)."""
from __future__ import annotations

import numpy as np
import torch

from ..runtime.constants import SH_C0, SH_C1, SH_C2, SH_C3


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """The real SH basis [N, (degree+1)^2] of 3DGS at unit directions dirs [N,3], degree <= 3."""
    x, y, z = dirs.unbind(-1)
    basis = [SH_C0 * torch.ones_like(x)]
    if degree > 0:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        basis += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * z * z - x * x - y * y),
                  SH_C2[3] * x * z, SH_C2[4] * (x * x - y * y)]
    if degree > 2:
        basis += [SH_C3[0] * y * (3 * x * x - y * y), SH_C3[1] * x * y * z,
                  SH_C3[2] * y * (4 * z * z - x * x - y * y), SH_C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y),
                  SH_C3[4] * x * (4 * z * z - x * x - y * y), SH_C3[5] * z * (x * x - y * y),
                  SH_C3[6] * x * (x * x - 3 * y * y)]
    return torch.stack(basis, -1)


def sh_to_rgb(means, sh, campos):
    """RGB [N,3] = max(0, SH(dir) . coefficients + 0.5), dir = normalize(mean - campos) (sh.cl), for
    sh [N,(d+1)^2,3]. numpy inputs: a float64 numpy result; tensors: a tensor in their dtype, with
    gradients (the color stage of :func:`qr_cl.render.rasterization`)."""
    as_numpy = not isinstance(sh, torch.Tensor)
    if as_numpy:
        means, sh, campos = (torch.as_tensor(np.asarray(a, np.float64)) for a in (means, sh, campos))
    campos = torch.as_tensor(campos, dtype=means.dtype)
    degree = int(round(sh.shape[1] ** 0.5)) - 1
    d = means - campos
    basis = sh_basis(d / d.norm(dim=1, keepdim=True), degree).to(sh.dtype)
    rgb = torch.clamp_min((basis[:, :, None] * sh).sum(1) + 0.5, 0.0)
    return rgb.numpy() if as_numpy else rgb
