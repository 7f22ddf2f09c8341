"""Numpy twin of sh.cl (:mod:`qr_cl.stages.sh`), in float64."""
from __future__ import annotations

import numpy as np

from ..runtime.constants import SH_C0, SH_C1, SH_C2, SH_C3


def sh_to_rgb(means, sh, campos) -> np.ndarray:
    """RGB [N,3] = max(0, SH(dir) . coefficients + 0.5), dir = normalize(mean - campos) (sh.cl)."""
    sh = np.asarray(sh, np.float64)
    degree = int(round(np.sqrt(sh.shape[1]))) - 1
    d = np.asarray(means, np.float64) - np.asarray(campos, np.float64)
    x, y, z = (d / np.linalg.norm(d, axis=1, keepdims=True)).T[:, :, None]
    basis = [SH_C0 * np.ones_like(x)]
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
    rgb = sum(bk * sh[:, i] for i, bk in enumerate(basis))
    return np.maximum(rgb + 0.5, 0.0)
