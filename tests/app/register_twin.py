"""Float64 twin of :func:`qr_cl.app.registration.register.register`, pixel by pixel, written to be read.

Each masked pixel walks its tile's depth-sorted list with the V-Render twin
(:func:`qr_cl.stages.select_ref.volume_select`: alpha_i and w_i = alpha_i T_i in float32, the
kernels' order of operations), keeps the K largest weights (ties: the nearer first) and adds w
times its masks' features to those Gaussians' float64 sums. It reads the kernel's own projection
and tile lists (a plan's ``meta()``), so it checks the contributors and the sums, not the
projection's rounding (which the stage twins test)."""
from __future__ import annotations

import numpy as np

from qr_cl.app.registration.register import ViewMasks
from qr_cl.runtime import TILE
from qr_cl.stages import select_ref


def register(metas: list[dict], views: list[ViewMasks], n: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Registered features [n,C] float64 (unit rows, zero where no masked pixel picks the
    Gaussian) and total weights [n] float64 of ``views`` (each with the ``meta()`` of its plan in
    ``metas``) through each masked pixel's ``k`` top contributors."""
    dim = views[0].features.shape[1]
    total, weight = np.zeros((n, dim)), np.zeros(n)
    for meta, view in zip(metas, views):
        tiles_x = -(-view.masks.shape[2] // TILE)
        features = view.features.astype(np.float64)
        for y, x in zip(*np.nonzero((view.masks >= 0).any(0))):
            start, end = meta["tile_ranges"][(y // TILE) * tiles_x + x // TILE]
            tile_ids = np.asarray(meta["flatten_ids"][start:end])
            pos, w, _ = select_ref.volume_select(select_ref.alphas(meta, tile_ids, np.array([[x, y]]))[0])
            keep = np.lexsort((pos, -w))[:k]
            picked, w_keep = tile_ids[pos[keep]], w[keep].astype(np.float64)
            feature = sum(features[m] for m in view.masks[:, y, x] if m >= 0)
            for g, wg in zip(picked, w_keep):
                total[g] += wg * feature
                weight[g] += wg
    norms = np.linalg.norm(total, axis=1, keepdims=True)
    return np.where(norms > 0, total / np.where(norms > 0, norms, 1), 0.0), weight
