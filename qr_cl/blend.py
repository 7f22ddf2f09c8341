"""Blend a Selection with per-Gaussian features (blend.cl), and the backward w.r.t. the features.

Features and images live on the device as rows of ``cstride`` floats (see
:func:`qr_cl.vrender.channel_layout`); the first ``channels`` floats of a row are meaningful.
"""
from __future__ import annotations


import numpy as np
import pyopencl.array as cla

from .raster import exclusive_scan
from .samplers import Selection
from .vrender import channel_layout

MAX_CHUNKS = 64               # rays are split into at most this many chunks for the transpose
MAX_HIST = 1 << 24            # ... and n_gaussians * chunks stays below this many ints



def _check_rows(array: cla.Array, rows: int, cstride: int, name: str) -> None:
    if array.shape != (rows, cstride) or array.dtype != np.float32:
        raise ValueError(f"{name} must be float32 [{rows}, {cstride}] on the device, got "
                         f"{array.dtype} {array.shape}")


def blend_forward(sel: Selection, features: cla.Array, channels: int,
                  background: np.ndarray | None = None, out: cla.Array | None = None) -> cla.Array:
    """image [P, cstride] = sum_j w[p,j] features[id[p,j]] (+ t_rem[p] * background).

    features: float32 [N, cstride] device rows (cstride from channel_layout(channels));
    background: [channels] or None (no background term); out: an optional float32 [P, cstride]
    device array to write into (reusing one avoids page faults on large fresh allocations).
    Rays as in the Selection; for the full image row p = y * width + x.
    """
    rt = sel.plan.runtime
    vw, nv, cstride = channel_layout(channels)
    _check_rows(features, sel.n_gaussians, cstride, "features")
    image = cla.empty(rt.queue, (sel.n_rays, cstride), np.float32) if out is None else out
    _check_rows(image, sel.n_rays, cstride, "out")
    if sel.n_rays == 0:
        return image
    bg = np.zeros(cstride, np.float32)
    if background is not None:
        bg[:channels] = np.asarray(background, np.float32).reshape(-1)[:channels]
    size, full = sel.launch()
    rt.kernel("blend.cl", "blend", VW=vw, NV=nv)(
        rt.queue, (size, cstride // (vw * nv)), None, sel.offsets.data, sel.count.data,
        sel.ids.data, sel.weights.data, features.data, np.int32(cstride), np.int32(full),
        np.int32(sel.plan.width), np.int32(sel.plan.height), np.int32(sel.plan.tiles_x),
        cla.to_device(rt.queue, bg).data, sel.t_rem.data, np.int32(background is not None),
        image.data)
    return image


def transpose(sel: Selection) -> tuple[cla.Array, cla.Array, cla.Array, int]:
    """The selection grouped by Gaussian (transpose.cl: stable counting sort, no atomics), cached
    on ``sel``.

    Returns (cursor [N * chunks] int32: cursor[(g+1) * chunks - 1] is the end of Gaussian g's
    segment, ray [E] int32 and weight [E] float32 per transposed entry, chunks). Within a
    Gaussian, entries are ordered by ray then by position in the ray.
    """
    if sel.transposed is None:
        rt, q = sel.plan.runtime, sel.plan.runtime.queue
        n, n_rays = sel.n_gaussians, sel.n_rays
        chunks = max(1, min(MAX_CHUNKS, n_rays, MAX_HIST // max(n, 1)))
        rays_per = -(-n_rays // chunks) if n_rays else 1
        cursor = cla.zeros(q, n * chunks, np.int32)
        total = int(cla.sum(sel.count).get()) if n_rays else 0
        t_ray = cla.empty(q, max(total, 1), np.int32)
        t_w = cla.empty(q, max(total, 1), np.float32)
        if n_rays:
            args = (np.int32(n_rays), np.int32(rays_per), np.int32(chunks), sel.offsets.data,
                    sel.count.data, sel.ids.data)
            rt.kernel("transpose.cl", "transpose_count")(q, (chunks,), None, *args, cursor.data)
            exclusive_scan(rt.context)(cursor)
            rt.kernel("transpose.cl", "transpose_fill")(q, (chunks,), None, *args, sel.weights.data,
                                                    cursor.data, t_ray.data, t_w.data)
        sel.transposed = (cursor, t_ray, t_w, chunks)
    return sel.transposed


def blend_backward(sel: Selection, dimage: cla.Array, channels: int) -> cla.Array:
    """dF [N, cstride] with dF[g] = sum over entries (p, j) with id[p,j] = g of w[p,j] dimage[p].

    dimage: float32 [P, cstride] device rows (the gradient of blend_forward's image). The sum order
    per Gaussian is fixed by :func:`transpose`, so repeated calls return identical bytes.
    """
    rt = sel.plan.runtime
    vw, nv, cstride = channel_layout(channels)
    _check_rows(dimage, sel.n_rays, cstride, "dimage")
    cursor, t_ray, t_w, chunks = transpose(sel)
    dfeatures = cla.empty(rt.queue, (sel.n_gaussians, cstride), np.float32)
    rt.kernel("blend.cl", "blend_backward", VW=vw, NV=nv)(
        rt.queue, (sel.n_gaussians, cstride // (vw * nv)), None, np.int32(chunks), cursor.data,
        t_ray.data, t_w.data, dimage.data, np.int32(cstride), dfeatures.data)
    return dfeatures
