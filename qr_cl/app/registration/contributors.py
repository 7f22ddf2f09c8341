"""A pixel's top contributors, as gsplat's ``rasterize_top_contributing_gaussian_ids`` and Dr.Splat
define them: the K Gaussians with the largest V-Render weights alpha_i T_i (T over every Gaussian in
front, the whole walk), in depth order, each with that weight.

The V-Render selection of the pixels holds every weight; the K largest of each ray are kept on the
host (ties: the nearer first, as the top-K sampler's twin orders them), so the weights are
the full render's, not a top-K sampler's re-composited ones."""
from __future__ import annotations

import numpy as np

from ...render import RasterPlan, select_rays


def top_contributors(plan: RasterPlan, pixels: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` top contributors of the rays ``pixels`` [P,2] (x, y) of ``plan``'s image: ids [P,k]
    int32 (Gaussians, -1 in slots past a ray's picks) and weights [P,k] float32 (alpha_i T_i, 0 in
    empty slots), picks in depth order and first in their row."""
    if k < 1:
        raise ValueError(f"k={k}: a pixel needs at least one contributor")
    host = select_rays(plan, "volume", 1, pixels).host()
    ids, weights = host["ids"], host["weights"]
    if ids.shape[1] > k:
        keep = np.sort(np.argsort(-weights, axis=1, kind="stable")[:, :k], axis=1)
        ids, weights = np.take_along_axis(ids, keep, 1), np.take_along_axis(weights, keep, 1)
    pad = k - ids.shape[1]
    if pad > 0:
        ids = np.pad(ids, ((0, 0), (0, pad)), constant_values=-1)
        weights = np.pad(weights, ((0, 0), (0, pad)))
    return np.ascontiguousarray(ids, np.int32), np.ascontiguousarray(weights, np.float32)
