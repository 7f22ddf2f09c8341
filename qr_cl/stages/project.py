"""Projection stage (project.cl): 3D Gaussians + pinhole camera -> 2D splats, TILE Gaussians per
work-item (as SIMD lanes), EWA with the 0.3 px low-pass of 3DGS. Twin: :mod:`qr_cl.stages.project_ref`."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pyopencl.array as cla

from ..runtime import BLOCK_GROUP, FOOTPRINT_INTS, SPLAT_FLOATS, TILE, Runtime, device_empty, to_device


def tile_grid(width: int, height: int) -> tuple[int, int]:
    """(tiles_x, tiles_y): TILE x TILE tiles covering a width x height image."""
    return (width + TILE - 1) // TILE, (height + TILE - 1) // TILE


def lane_items(n: int) -> int:
    """Global size of a kernel with TILE Gaussians per work-item (project.cl) for N = ``n``, in
    whole work-groups of :data:`~qr_cl.runtime.BLOCK_GROUP` (work-items past N return at once)."""
    return -(-n // (TILE * BLOCK_GROUP[0])) * BLOCK_GROUP[0]


class Projection(NamedTuple):
    """The outputs of :func:`project`, device arrays over the N Gaussians: splats [N,8] float32
    (mean2d px, conic, opacity, depth and sigma_max, in the slots of
    :data:`~qr_cl.runtime.SPLAT`), radii [N,2] int32 (x, y: the
    half-sides in px of the opacity-aware box the Gaussian is binned within, at most its 3-sigma
    radius; 0 = culled), footprints [N, FOOTPRINT_INTS] int32 (the tile rectangle [x0, y0, x1, y1)
    in FOOTPRINT_RECT, the tiles of its rows that the blend ellipse reaches packed in
    FOOTPRINT_SPANS: see :mod:`qr_cl.runtime.constants`), tiles_touched [N] int32 (the tiles of those rows) and depth_keys [N] int32
    (the bits of the positive float32 depth, ordered as the depths; INT32_MAX for culled
    Gaussians)."""

    splats: cla.Array
    radii: cla.Array
    footprints: cla.Array
    tiles_touched: cla.Array
    depth_keys: cla.Array


def project(rt: Runtime, means: cla.Array, quats: cla.Array, scales: cla.Array, opacities: cla.Array,
            viewmat: np.ndarray, K: np.ndarray, width: int, height: int, near: float, far: float) -> Projection:
    """Run project.cl on device arrays means [N,3], quats [N,4] (unit w,x,y,z), scales [N,3],
    opacities [N] (activated), for viewmat [4,4] world-to-camera and K [3,3] (px), near/far planes
    (camera z, world units)."""
    n = means.shape[0]
    tiles_x, tiles_y = tile_grid(width, height)
    splats = device_empty(rt, (n, SPLAT_FLOATS), np.float32)
    radii = device_empty(rt, (n, 2), np.int32)
    footprints = device_empty(rt, (n, FOOTPRINT_INTS), np.int32)
    touched, depth_keys = device_empty(rt, n, np.int32), device_empty(rt, n, np.int32)
    rt.launch("project", lane_items(n), local_size=BLOCK_GROUP, n=n, means=means, quats=quats, scales=scales,
              opacities=opacities, viewmat=to_device(rt, np.asarray(viewmat).reshape(16)),
              fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=width, height=height,
              near=near, far=far, tiles_x=tiles_x, tiles_y=tiles_y,
              splats=splats, radii=radii, footprints=footprints, tiles_touched=touched, depth_keys=depth_keys)
    return Projection(splats, radii, footprints, touched, depth_keys)


def project_backward(rt: Runtime, means: cla.Array, quats: cla.Array, scales: cla.Array, radii: cla.Array,
                     viewmat: np.ndarray, K: np.ndarray, width: int, height: int, d_splats: cla.Array,
                     view_grads: bool = False) -> tuple[cla.Array, cla.Array, cla.Array, np.ndarray | None]:
    """The projection's backward (project_backward in project.cl): dL/dsplats [N,8] (d mean2d x, y
    px; d conic A, B, C; unread; d depth; unread) -> (d means [N,3], d quats [N,4] of the
    unit-quaternion rotation formula, d scales [N,3]) float32 device arrays, zero for culled
    Gaussians (radii 0), and with ``view_grads`` d viewmat [4,4] float64 (the kernel's per-Gaussian
    shares summed on the host in float64, in a fixed order; its last row 0), else None. Inputs as
    :func:`project`."""
    n = means.shape[0]
    d_means, d_scales = device_empty(rt, (n, 3), np.float32), device_empty(rt, (n, 3), np.float32)
    d_quats = device_empty(rt, (n, 4), np.float32)
    d_views = device_empty(rt, (n, 12) if view_grads else 1, np.float32)
    rt.launch("project_backward", lane_items(n), local_size=BLOCK_GROUP, n=n, means=means, quats=quats, scales=scales,
              viewmat=to_device(rt, np.asarray(viewmat, np.float32).reshape(16)),
              fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=width, height=height, radii=radii,
              d_splats=d_splats, d_means=d_means, d_quats=d_quats, d_scales=d_scales,
              view_grads=int(view_grads), d_views=d_views)
    d_viewmat = None
    if view_grads:
        shares = d_views.get().astype(np.float64).sum(0)      # [d W row-major | d t]
        d_viewmat = np.zeros((4, 4))
        d_viewmat[:3, :3], d_viewmat[:3, 3] = shares[:9].reshape(3, 3), shares[9:]
    return d_means, d_quats, d_scales, d_viewmat
