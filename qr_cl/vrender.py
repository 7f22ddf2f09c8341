"""Fused V-Render (full alpha blending without a stored selection) and SH colours, host side."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from .device import Runtime
from .raster import TILE, RasterPlan, host_output, to_device


def channel_layout(channels: int) -> tuple[int, int, int]:
    """(VW, NV, cstride) for ``channels`` feature channels.

    VW is the vector width of the kernel (16 from 16 channels up, else the next power of two),
    NV the vectors a work-item accumulates (4, 2 or 1, whichever divides the vector count), and
    cstride the padded row length in floats (a multiple of VW * NV).
    """
    if channels < 1:
        raise ValueError(f"features need at least one channel, got {channels}")
    vw = 16 if channels >= 16 else 1 << (channels - 1).bit_length()
    n_vec = -(-channels // vw)
    nv = 4 if n_vec % 4 == 0 else 2 if n_vec % 2 == 0 else 1
    return vw, nv, n_vec * vw


def padded_rows(features: np.ndarray, cstride: int) -> np.ndarray:
    """features [N,C] as a C-contiguous float32 [N,cstride] array (zero columns appended)."""
    features = np.asarray(features, np.float32)
    if features.shape[1] == cstride:
        return np.ascontiguousarray(features)
    out = np.zeros((features.shape[0], cstride), np.float32)
    out[:, :features.shape[1]] = features
    return out


def sh_colors(rt: Runtime, means: cla.Array, sh: np.ndarray, campos: np.ndarray) -> cla.Array:
    """View-dependent RGB [N,4] (4th channel 0) from SH coefficients sh [N,(d+1)^2,3], d <= 3."""
    n, k = sh.shape[:2]
    degree = int(round(np.sqrt(k))) - 1
    if (degree + 1) ** 2 != k or degree > 3 or sh.shape[2] != 3:
        raise ValueError(f"SH coefficients must be [N, (d+1)^2, 3] with d <= 3, got {sh.shape}")
    colors = cla.zeros(rt.queue, (max(n, 1), 4), np.float32)
    if n:
        rt.kernel("sh.cl", "sh_to_rgb", DEGREE=degree)(
            rt.queue, (n,), None, np.int32(n), means.data, to_device(rt, sh).data,
            np.array([*campos, 0], np.float32), colors.data)
    return colors[:n]


def render_fused(plan: RasterPlan, features: cla.Array, channels: int,
                 background: np.ndarray | None = None,
                 out: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Blend every Gaussian V-Render uses (alpha >= 1/255, until T <= 1e-4) in one kernel.

    features [N, cstride] on the device with cstride from :func:`channel_layout` (channels);
    background [channels] or None. Returns image [H,W,channels], alpha [H,W,1] (1 - T) and
    expected depth [H,W,1] (sum of w_i z_i / (1 - T); 0 where nothing was hit), float32.
    ``out``: an optional C-contiguous float32 [H,W,cstride] host array to render into (reusing one
    avoids the page faults of a fresh large allocation); with C == cstride the image is a view of it.
    """
    rt = plan.runtime
    vw, nv, cstride = channel_layout(channels)
    if features.shape[-1] != cstride:
        raise ValueError(f"features have row length {features.shape[-1]}, expected {cstride}")
    h, w = plan.height, plan.width
    image = np.empty((h, w, cstride), np.float32) if out is None else out
    if image.shape != (h, w, cstride) or image.dtype != np.float32 or not image.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous float32 array of shape {(h, w, cstride)}")
    alpha = cla.empty(rt.queue, h * w, np.float32)
    depth = cla.empty(rt.queue, h * w, np.float32)
    bg = np.zeros(cstride, np.float32)
    if background is not None:
        bg[:channels] = np.asarray(background, np.float32).reshape(-1)[:channels]
    n_pix = plan.tiles_x * plan.tiles_y * TILE * TILE
    with host_output(rt, image) as image_buf:
        rt.kernel("vrender.cl", "vrender", VW=vw, NV=nv)(
            rt.queue, (n_pix,), None, plan.ranges.data, plan.ids.data, plan.splats.data,
            features.data, np.int32(cstride), np.int32(w), np.int32(h), np.int32(plan.tiles_x),
            to_device(rt, bg).data, np.int32(background is not None), image_buf, alpha.data, depth.data)
    img = image if cstride == channels else np.ascontiguousarray(image[:, :, :channels])
    return img, alpha.get().reshape(h, w, 1), depth.get().reshape(h, w, 1)
