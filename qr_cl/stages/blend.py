"""Blend stage (blend.cl): a Selection blended with per-Gaussian features, and the backward
w.r.t. the features over the selection's transpose. Twin: :mod:`qr_cl.stages.blend_ref`.

Features and images are device rows of ``cstride`` floats (:func:`qr_cl.runtime.channel_layout`).
Both functions write into ``out`` when given one (e.g. a :func:`qr_cl.runtime.shared_array` over
a host array: the result then lands in host memory without a copy on CPU devices), else into a
device array from the runtime's pool.
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..runtime import channel_layout, check_buffer, device_empty, padded_vector, to_device
from .select import Selection


def _check_rows(array: cla.Array, rows: int, cstride: int, name: str) -> None:
    if array.shape != (rows, cstride) or array.dtype != np.float32:
        raise ValueError(f"{name} must be float32 [{rows}, {cstride}] on the device, got "
                         f"{array.dtype} {array.shape}")


def blend_forward(sel: Selection, features: cla.Array, channels: int,
                  background: np.ndarray | None = None, out: cla.Array | None = None) -> cla.Array:
    """image [P, cstride] = sum_j w[p,j] features[id[p,j]] (+ t_rem[p] * background).

    features: float32 [N, cstride] device rows (cstride from channel_layout(channels));
    background: [channels] or None (no background term); out: an optional float32 [P, cstride]
    device array to write into (else one from the runtime's memory pool).
    Rays as in the Selection; for the full image row p = y * width + x.
    """
    rt = sel.plan.runtime
    vw, nv, cstride = channel_layout(channels, rt.gpu_shaped)
    _check_rows(features, sel.n_gaussians, cstride, "features")
    check_buffer(rt, 4 * sel.n_rays * cstride, f"the image of {sel.n_rays} rays x {cstride} channels")
    image = device_empty(rt, (sel.n_rays, cstride), np.float32) if out is None else out
    _check_rows(image, sel.n_rays, cstride, "out")
    if sel.n_rays == 0:
        return image
    size, full = sel.launch()
    plan = sel.plan
    rt.launch("blend", (size, cstride // (vw * nv)), defines={"VW": vw, "NV": nv},
              offsets=sel.offsets, count=sel.count, sel_ids=sel.ids, sel_w=sel.weights,
              features=features, cstride=cstride, full=full, n_rays=sel.n_rays, width=plan.width,
              height=plan.height,
              tiles_x=plan.tiles_x, background=to_device(rt, padded_vector(background, channels, cstride)),
              t_rem=sel.t_rem, use_bg=background is not None, image=image)
    return image


def blend_backward(sel: Selection, dimage: cla.Array, channels: int, out: cla.Array | None = None) -> cla.Array:
    """dF [N, cstride] with dF[g] = sum over entries (p, j) with id[p,j] = g of w[p,j] dimage[p].

    dimage: float32 [P, cstride] device rows (the gradient of blend_forward's image); out: an
    optional float32 [N, cstride] device array to write into (else one from the runtime's pool).
    The sum order per Gaussian is fixed by :meth:`Selection.transpose`, so repeated calls return
    identical bytes.
    """
    rt = sel.plan.runtime
    vw, nv, cstride = channel_layout(channels, rt.gpu_shaped)
    _check_rows(dimage, sel.n_rays, cstride, "dimage")
    check_buffer(rt, 4 * sel.n_gaussians * cstride, f"dF of {sel.n_gaussians} Gaussians x {cstride} channels")
    cursor, t_ray, t_w, chunks = sel.transpose()
    dfeatures = device_empty(rt, (sel.n_gaussians, cstride), np.float32) if out is None else out
    _check_rows(dfeatures, sel.n_gaussians, cstride, "out")
    rt.launch("blend_backward", (sel.n_gaussians, cstride // (vw * nv)), defines={"VW": vw, "NV": nv},
              n=sel.n_gaussians, order=sel.backward_order(), n_chunks=chunks, cursor=cursor, t_ray=t_ray,
              t_w=t_w, dimage=dimage, cstride=cstride,
              dfeatures=dfeatures)
    return dfeatures
