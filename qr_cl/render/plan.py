"""The geometry of one render: project, then bin and sort (a RasterPlan)."""
from __future__ import annotations

import numpy as np

from ..runtime import Runtime, to_device
from ..stages import RasterPlan, bin_and_sort, project


def make_plan(rt: Runtime, means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
              viewmat: np.ndarray, K: np.ndarray, width: int, height: int, near: float = 0.01,
              far: float = 1e10) -> RasterPlan:
    """Project, bin and sort Gaussians for one camera (geometry only) on the runtime ``rt``.

    means [N,3], quats [N,4] unit w,x,y,z, scales [N,3] activated, opacities [N] activated (float32
    host arrays, N >= 1); viewmat [4,4] world-to-camera; K [3,3] intrinsics in px; width/height in px.
    The public call is :func:`qr_cl.render.rasterize_plan` (on the checked runtime by default).
    """
    dev = [to_device(rt, a) for a in (means, quats, scales, opacities)]
    proj = project(rt, *dev, viewmat, np.asarray(K), width, height, near, far)
    ranges, ids, n_keys = bin_and_sort(rt, proj, width, height)
    return RasterPlan(runtime=rt, width=int(width), height=int(height), splats=proj.splats, radii=proj.radii,
                      ranges=ranges, ids=ids, n_keys=n_keys)
