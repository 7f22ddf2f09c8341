"""Fused V-Render stage (vrender.cl): full alpha blending of a RasterPlan without a stored
selection, one kernel per image (the speed baseline; no gradients): the block walk on CPU shapes,
the tile walk on GPU shapes, in windows on a device with a loop limit. Twin:
:mod:`qr_cl.stages.vrender_ref`."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..runtime import (BLOCK_GROUP, TILE, VOLUME_STATE_FLOATS, channel_layout, check_buffer, device_empty, host_empty,
                       padded_vector, shared_array, streamed, to_device, walk_windows)
from .binning import RasterPlan
from .blend import row_defines

#: GPU shapes: the vectors of VW channels a tile_vrender work-item blends (its channel group; each
#: group walks the tile list again, as gsplat's channel chunks do).
GPU_VECTORS = 2


def render_fused(plan: RasterPlan, features: cla.Array, channels: int,
                 background: np.ndarray | None = None, out: np.ndarray | None = None, row0: int = 0,
                 accumulate: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blend every Gaussian V-Render uses (alpha >= 1/255, until T <= 1e-4) in one kernel.

    features [R, cstride] float32 or float16 (read as half, blended in float32) on the device with
    cstride from :func:`channel_layout` (channels): the table's rows [row0, row0 + R), all N or a
    row part (the other Gaussians are walked, not blended);
    background [channels] or None. Returns image [H,W,channels], alpha [H,W,1] (1 - T) and
    expected depth [H,W,1] (sum of w_i z_i / (1 - T); 0 where nothing was hit), float32.
    ``out``: an optional C-contiguous float32 [H,W,cstride] host array to render into (reusing one
    avoids the page faults of a fresh large allocation); the image is a view of it ([H,W,C] of
    [H,W,cstride]), as it is of the pooled host array used without ``out``. ``accumulate``: add the
    blend to ``out`` (the row parts after the first).
    """
    rt = plan.runtime
    vw, nv, cstride = channel_layout(channels, rt.gpu_shaped)
    if features.shape[-1] != cstride or features.dtype not in (np.float32, np.float16):
        raise ValueError(f"features must be float32 or float16 rows of length {cstride}, got {features.dtype} "
                         f"rows of length {features.shape[-1]}")
    if row0 < 0 or row0 + features.shape[0] > plan.n_gaussians:
        raise ValueError(f"features must be rows of the {plan.n_gaussians} Gaussians, got rows "
                         f"[{row0}, {row0 + features.shape[0]})")
    if accumulate and out is None:
        raise ValueError("render_fused(accumulate=True) adds to an image: pass it as out")
    h, w = plan.height, plan.width
    check_buffer(rt, 4 * h * w * cstride, f"the fused V-Render image of {w}x{h} px x {cstride} channels "
                 "(rasterize(..., sampler='volume') renders it in chunks)")
    image = host_empty((h, w, cstride)) if out is None else out
    if image.shape != (h, w, cstride) or image.dtype != np.float32 or not image.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {(h, w, cstride)}")
    alpha, depth = device_empty(rt, h * w), device_empty(rt, h * w)
    if rt.gpu_shaped:          # the tile walk: a work-group per tile, a work-item per pixel and channel group
        nv = GPU_VECTORS if (cstride // vw) % GPU_VECTORS == 0 else 1
        size = (plan.tiles_x * plan.tiles_y * TILE * TILE, cstride // (vw * nv))
        kernel, local, loops = "tile_vrender", (rt.group_rays, 1), nv + 6
    else:                      # the block walk: BATCH-Gaussian flushes of TILE rows x cstride / VW vectors
        size, kernel, local = plan.tiles_x * plan.tiles_y * TILE, "vrender", BLOCK_GROUP
        loops = 2 * TILE * (cstride // vw) + TILE + 4
    windows = walk_windows(rt.loop_limit, plan.longest_list if rt.loop_limit else 0, loops)
    states = [device_empty(rt, (h * w if len(windows) > 1 else 1) * VOLUME_STATE_FLOATS, np.float32) for _ in range(2)]
    with shared_array(rt, image, "rw" if accumulate or len(windows) > 1 else "w") as image_dev:
        for i, (walk_from, walk_to) in enumerate(windows):
            rt.launch(kernel, size, defines={"VW": vw, "NV": nv, **row_defines(features)}, local_size=local,
                      ranges=plan.ranges, ids=plan.ids, splats=plan.splats, features=features, row0=row0,
                      n_rows=features.shape[0], cstride=cstride, width=w, height=h, tiles_x=plan.tiles_x,
                      background=to_device(rt, padded_vector(background, channels, cstride)),
                      use_bg=background is not None, accumulate=accumulate, stream=streamed(image.nbytes),
                      image=image_dev, alpha=alpha, depth=depth, walk_from=walk_from, walk_to=walk_to,
                      state_in=states[i % 2], state_out=states[1 - i % 2])
    return (image[:, :, :channels], alpha.get(ary=host_empty(h * w)).reshape(h, w, 1),
            depth.get(ary=host_empty(h * w)).reshape(h, w, 1))
