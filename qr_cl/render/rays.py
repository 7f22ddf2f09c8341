"""Rays of one camera, selected and blended: the one API through which the engine
(:func:`~qr_cl.render.engine.render_view`) and the app's paths (training, registration,
evaluation labels, experiments) select rays and blend tables through them.

A camera's rays are its plan (:func:`~qr_cl.render.rasterize_plan`: projection and tile lists)
and its pixels (None: the whole image, ray p = y * width + x; else pixels [P,2] (x, y), ray p =
row p). Selected by a sampler with K (:func:`select_rays`) they are a
:class:`~qr_cl.stages.Selection`, a value; selections made from selections (:func:`gather_rays`,
:func:`concat_selections`, :func:`compact_selections`, :func:`listed_selection`) are too. A
selection is blended with torch feature tables here (:func:`blend_rays`, or
:func:`select_and_blend_rays`: selection and first blend in one stage call), the table taken in
row parts where it exceeds a device buffer, the image written straight into host memory; and
:func:`weighted_sums` is the blend's transpose (each Gaussian's sum of its entries' weights times
per-ray values: the feature gradient, registration's sums). Gradients through these are
:mod:`qr_cl.render.autograd`'s."""
from __future__ import annotations

import numpy as np
import torch

from ..runtime import (DEFAULTS, Runtime, channel_layout, device_rows, host_empty, row_parts, shared_array,
                       table_parts)
from ..stages import (BackwardIndex, RasterPlan, Selection, blend_backward, blend_forward, check_pixels,
                      compact_selections, concat_selections, entry_bytes, gather_rays, listed_selection,
                      prepare_backward, ray_entries, rows_to_half, select, select_and_blend)

#: This API: its functions, and the stages' selection types and operations it passes on as they are.
__all__ = ["BackwardIndex", "RasterPlan", "Selection", "blend_rays", "compact_selections", "concat_selections",
           "gather_rays", "host_rows", "image_dtype", "image_pixels", "listed_selection", "prepare_backward",
           "ray_entries", "ray_sets", "select_and_blend_rays", "select_rays", "table_rows", "weighted_sums"]


def host_rows(tensor: torch.Tensor) -> np.ndarray:
    """A numpy view of a [R, C] tensor's rows (float32 on the CPU; converted only otherwise)."""
    return tensor.detach().to("cpu", torch.float32).numpy()


def table_rows(features: torch.Tensor) -> np.ndarray:
    """A numpy view of a feature table [N, C]: a float16 table stays float16 (the kernels read it
    as half and blend in float32), any other is :func:`host_rows`."""
    if features.dtype == torch.float16:
        return features.detach().to("cpu").numpy()
    return host_rows(features)


def image_dtype(features: torch.Tensor) -> torch.dtype:
    """The dtype of a blend of ``features``: theirs, at least float32 (a float16 table's image
    keeps the float32 sums)."""
    return torch.promote_types(features.dtype, torch.float32)


def _output(rows: int, channels: int, cstride: int, dtype=np.float32) -> tuple[np.ndarray, torch.Tensor]:
    """A pooled host array [rows, cstride] of ``dtype`` the kernels write into, and the [rows,
    channels] tensor over it that the caller receives (a strided view when channels < cstride)."""
    host = host_empty((rows, cstride), dtype)
    return host, torch.from_numpy(host if cstride == channels else host[:, :channels])


def image_pixels(width: int, height: int) -> np.ndarray:
    """Every pixel (x, y) of a width x height image, row-major: [H*W, 2] int32."""
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.int32)


def ray_sets(rt: Runtime, width: int, height: int, pixels: np.ndarray | None, k: int,
             cstride: int) -> list[np.ndarray | None]:
    """The rays of a render in sets whose image rows ([P, cstride] floats) and dense selection
    rows ([P, K], and their transpose's keys: :func:`~qr_cl.stages.entry_bytes`) fit in one
    device buffer: ``[pixels]`` when everything fits (None = the whole image), else consecutive
    runs of the pixel coordinates [P_i, 2] (x, y), row-major for the whole image, so
    concatenating the sets' rows gives the image."""
    n_rays = width * height if pixels is None else len(pixels)
    per_ray = max(4 * cstride, entry_bytes(rt) * k)
    if n_rays * per_ray <= rt.max_buffer_bytes:
        return [pixels]
    pixels = image_pixels(width, height) if pixels is None else pixels
    step = max(1, rt.max_buffer_bytes // per_ray)
    return [pixels[i:i + step] for i in range(0, n_rays, step)]


def select_rays(plan: RasterPlan, sampler: str = DEFAULTS.sampler, k: int = DEFAULTS.k,
                pixels: np.ndarray | None = None) -> Selection:
    """The Selection of ``sampler`` ("volume", "quantile", "topk" or "stratified"; K = ``k``,
    ignored by volume) of ``plan``'s whole image or of its rays ``pixels`` [P,2] (x, y) px
    (:func:`qr_cl.stages.select`). Cost grows with the rays (and their tile lists)."""
    return select(plan, sampler, k, pixels)


def blend_rays(selection: Selection, features: torch.Tensor, background: torch.Tensor | None = None) -> torch.Tensor:
    """image [P,C] (:func:`image_dtype`; no graph: :func:`qr_cl.render.blend` differentiates) of
    ``selection`` blended with ``features`` [N,C] (float32 or float16) and ``background`` [C]
    (or None), written into a pooled host array: the blend of each row part of the table added
    up, the background with the first."""
    rt = selection.plan.runtime
    channels, table, bg = features.shape[1], table_rows(features), _host_background(background)
    cstride = channel_layout(channels)[2]
    host, image = _output(selection.n_rays, channels, cstride)
    with shared_array(rt, host, "w") as out:
        for r0, rows in table_parts(rt, table, cstride):
            blend_forward(selection, rows, channels, None if r0 else bg, out=out, row0=r0, accumulate=r0 > 0)
    return image.to(image_dtype(features))


def select_and_blend_rays(plan: RasterPlan, sampler: str, k: int, pixels: np.ndarray | None, features: torch.Tensor,
                          background: torch.Tensor | None = None) -> tuple[Selection, torch.Tensor]:
    """(the Selection of :func:`select_rays`, its image of :func:`blend_rays`) in one stage call
    (:func:`qr_cl.stages.select_and_blend`: where it can, each ray is blended in the selection
    kernel right after it is selected): the same selection and image bytes as the two calls. The
    row parts of a table beyond a device buffer after the first are blended after it."""
    rt = plan.runtime
    pixels = None if pixels is None else check_pixels(pixels, plan.width, plan.height)
    channels, table, bg = features.shape[1], table_rows(features), _host_background(background)
    cstride = channel_layout(channels)[2]
    host, image = _output(plan.width * plan.height if pixels is None else len(pixels), channels, cstride)
    sel = None
    with shared_array(rt, host, "w") as out:
        for r0, rows in table_parts(rt, table, cstride):
            if sel is None:
                sel, _ = select_and_blend(plan, sampler, k, pixels, rows, channels, bg, out)
            else:
                blend_forward(sel, rows, channels, out=out, row0=r0, accumulate=True)
    return sel, image.to(image_dtype(features))


def weighted_sums(selection: Selection, values: torch.Tensor | np.ndarray, dtype: torch.dtype = torch.float32,
                  backward_index: BackwardIndex | None = None) -> torch.Tensor:
    """[N,C] in ``dtype`` (the feature table's): per Gaussian g of the selection's table, the
    sum over its entries (p, j) of w[p,j] values[p] (``values`` [P,C], one row per ray): the
    blend's transpose, i.e. the gradient of a loss w.r.t. the features given ``values`` =
    dL/dimage. Deterministic (:func:`qr_cl.stages.blend_backward`), summed in float32 (a float16
    result is rounded on the device), a row part at a time where the rows exceed a device buffer.
    ``backward_index``: the selection's (:func:`prepare_backward`), kept by the caller (None:
    made for this call)."""
    rt = selection.plan.runtime
    rows = host_rows(values) if isinstance(values, torch.Tensor) else np.ascontiguousarray(values, np.float32)
    channels = rows.shape[1]
    cstride = channel_layout(channels)[2]
    index = BackwardIndex() if backward_index is None else backward_index
    half = dtype == torch.float16
    host, sums = _output(selection.n_gaussians, channels, cstride, np.float16 if half else np.float32)
    with device_rows(rt, rows, cstride) as dimage:
        for r0, r1 in row_parts(rt, selection.n_gaussians, cstride):
            with shared_array(rt, host[r0:r1], "w") as out:
                if half:
                    rows_to_half(rt, blend_backward(selection, dimage, channels, row0=r0, n_rows=r1 - r0,
                                                    backward_index=index), out)
                else:
                    blend_backward(selection, dimage, channels, out=out, row0=r0, n_rows=r1 - r0,
                                   backward_index=index)
    return sums.to(dtype)


def _host_background(background: torch.Tensor | None) -> np.ndarray | None:
    """A background tensor [C] as a host array (None stays None)."""
    return None if background is None else background.detach().cpu().numpy()
