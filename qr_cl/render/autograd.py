"""torch autograd through the renderer.

:class:`BlendFunction`: gradients w.r.t. per-Gaussian features (and background) through a given
Selection (GS-Net: the Gaussians are frozen, so the geometry is a constant of the graph).
A render of one camera with gradients w.r.t. the Gaussians is two Functions, with gsplat's 2-D
tensors between them: :class:`ProjectFunction` (means, quats, scales, viewmat -> means2d, conics,
depths of the plan's splats) and :class:`RasterFunction` (means2d, conics, opacities, features,
background -> image, alpha through a Selection, which is piecewise constant in the geometry).
:class:`SHColors`: the color stage (sh.cl), with gradients w.r.t. SH coefficients, means and the
camera centre.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from ..runtime import SPLAT, SPLAT_FLOATS, Runtime, channel_layout, check_channels, device_empty, device_rows, table_parts, to_device
from ..stages import (BackwardIndex, RasterPlan, Selection, blend_backward_alpha, project_backward, sh_backward, sh_colors,
                      splat_backward, weight_grads)
from .rays import blend_rays, host_rows, table_rows, weighted_sums


class BlendFunction(torch.autograd.Function):
    """image [P,C] = blend(selection, features [N,C]) (+ t_rem * background [C]).

    No copies where the memory allows it: forward reads the features in place (float32 or
    float16, C-contiguous, C == cstride; else padded once into a pooled host array) and writes the image
    straight into the memory of the tensor it returns (a pooled host array that no earlier
    output still uses; [P, cstride] with a [P, C] view returned when C < cstride); backward
    likewise reads dImage in place and writes dF straight into the returned gradient. On devices
    that do not share host memory the same calls copy through pooled device buffers. A table (or
    dF) larger than the device's largest buffer is taken in row parts (:func:`row_parts`), each
    read in place: the image is the sum of their blends, dF written a part's rows at a time. The
    backward is :func:`blend_backward` (deterministic: a fixed sum order per Gaussian); the
    background gets its gradient sum_p t_rem[p] dImage[p]. The selection gets none. A float16
    table gives a float32 image and a float16 gradient (summed in float32, then rounded).
    ``backward_index``: the selection's :class:`~qr_cl.stages.BackwardIndex`, kept with it by the caller
    (None: the Function keeps its own).
    """

    @staticmethod
    def forward(ctx, features: torch.Tensor, selection: Selection, background: torch.Tensor | None,
                backward_index: BackwardIndex | None):
        ctx.selection, ctx.channels, ctx.dtype = selection, features.shape[1], features.dtype
        ctx.backward_index = BackwardIndex() if backward_index is None else backward_index
        return blend_rays(selection, features, background)

    @staticmethod
    def backward(ctx, grad_image: torch.Tensor):
        sel = ctx.selection
        d_features = weighted_sums(sel, grad_image, ctx.dtype, ctx.backward_index) if ctx.needs_input_grad[0] else None
        d_background = _background_grad(sel, grad_image) if ctx.needs_input_grad[2] else None
        return d_features, None, d_background, None


def _background_grad(sel: Selection, grad_image: torch.Tensor) -> torch.Tensor:
    """dL/dbackground [C] = sum_p t_rem[p] dImage[p]."""
    return torch.from_numpy(sel.t_rem.get()[:sel.n_rays]).to(grad_image.dtype) @ grad_image


def blend(selection: Selection, features: torch.Tensor, background: torch.Tensor | None = None,
          backward_index: BackwardIndex | None = None) -> torch.Tensor:
    """Differentiable blend: features [N,C] float tensor (C in 1..2048) -> image [P,C] (rays of the
    selection; for the whole image row p = y * width + x). Computed in float32 on the device (a
    float16 table read as half) and returned in features' dtype, at least float32. Gradients flow
    to features (in their dtype) and background only. ``backward_index``: what the backward reads of the
    selection, kept by the caller (e.g. made ahead by :func:`qr_cl.stages.prepare_backward`)."""
    if features.ndim != 2 or features.shape[0] != selection.n_gaussians:
        raise ValueError(f"features must be [{selection.n_gaussians}, C], got {tuple(features.shape)}")
    check_channels(features.shape[1])
    if background is not None and tuple(background.shape) != (features.shape[1],):
        raise ValueError(f"background must be [{features.shape[1]}], got {tuple(background.shape)}")
    return BlendFunction.apply(features, selection, background, backward_index)


@dataclass(frozen=True)
class View:
    """What a render of one camera needs besides the Gaussians: camera (viewmat [4,4]
    world-to-camera, K [3,3] px, width, height px, near/far camera z), sampler and K, and the rays
    (pixels [P,2] (x, y) or None for the whole image, ray p = y * width + x)."""

    viewmat: np.ndarray
    K: np.ndarray
    width: int
    height: int
    near: float = 0.01
    far: float = 1e10
    sampler: str = "volume"
    k: int = 0
    pixels: np.ndarray | None = None


def _to_tensor(array: np.ndarray, like: torch.Tensor) -> torch.Tensor:
    """A float host array as a tensor of ``like``'s dtype."""
    return torch.from_numpy(np.ascontiguousarray(array)).to(like.dtype)


class ProjectFunction(torch.autograd.Function):
    """(means2d [C,N,2] px, conics [C,N,3] (A, B, C: the inverse 2D covariance), depths [C,N]
    camera z) of the splats of ``plans`` (one per camera: the projection of means [N,3], unit
    quats [N,4] and scales [N,3] by viewmats [C,4,4] for ``views``; zeros for culled Gaussians),
    stacked on the host.

    Backward by project.cl's ``project_backward`` per camera (16 Gaussians per work-item, no sums
    across Gaussians), the cameras' shares added in camera order, to means, quats, scales and,
    when they need one, the viewmats: each camera's per-Gaussian shares of dL/dviewmat summed on
    the host in float64, in a fixed order (deterministic). The intrinsics get no gradient.
    """

    @staticmethod
    def forward(ctx, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, viewmats: torch.Tensor,
                plans: list[RasterPlan], views: list[View]):
        splats = np.stack([plan.splats.get() for plan in plans])
        ctx.plans, ctx.views = plans, views
        ctx.save_for_backward(means, quats, scales, viewmats)
        return (_to_tensor(splats[..., SPLAT.mean], means), _to_tensor(splats[..., SPLAT.conic], means),
                _to_tensor(splats[..., SPLAT.depth], means))

    @staticmethod
    def backward(ctx, d_means2d: torch.Tensor, d_conics: torch.Tensor, d_depths: torch.Tensor):
        means, quats, scales, viewmats = ctx.saved_tensors
        rt = ctx.plans[0].runtime
        d_splats = np.zeros((len(ctx.plans), means.shape[0], SPLAT_FLOATS), np.float32)
        for cols, grad in ((SPLAT.mean, d_means2d), (SPLAT.conic, d_conics), (SPLAT.depth, d_depths)):
            if grad is not None:
                d_splats[..., cols] = host_rows(grad)
        dev = [to_device(rt, host_rows(t)) for t in (means, quats, scales)]
        sums = [np.zeros(t.shape, np.float32) for t in (means, quats, scales)]
        d_views = np.zeros((len(ctx.plans), 4, 4))
        for c, (plan, view) in enumerate(zip(ctx.plans, ctx.views)):
            *grads, d_view = project_backward(rt, *dev, plan.radii, view.viewmat, view.K, view.width, view.height,
                                              to_device(rt, d_splats[c]), view_grads=ctx.needs_input_grad[3])
            for total, grad in zip(sums, grads):
                total += grad.get()
            if d_view is not None:
                d_views[c] = d_view
        grads = [_to_tensor(total, means) if need else None for total, need in zip(sums, ctx.needs_input_grad[:3])]
        return (*grads, _to_tensor(d_views, viewmats) if ctx.needs_input_grad[3] else None, None, None)


#: A callback that receives a render's |dL/dmean2d| sums [N,2] (gsplat's absgrad, see RasterFunction).
AbsGradSink = Callable[[np.ndarray], None]


class RasterFunction(torch.autograd.Function):
    """(image [P,C], alpha [P,1]) = the blend of one camera's Selection (of ``selection.plan``,
    whose splats are means2d [N,2], conics [N,3] and opacities [N]) with features [N,C] and
    background [C] or None; alpha = 1 - the transmittance where the walk stopped. The tensors
    means2d, conics (None when no gradient is wanted: the kernels read the plan's splats) and
    opacities are the values of the plan's splats: :class:`ProjectFunction`'s outputs (or views of
    gsplat's meta tensors built from them).

    Backward (deterministic: every per-Gaussian sum runs over the selection's transpose in a fixed
    order): features and background as :class:`BlendFunction`; means2d, conics and opacities by
    weight_grads (dL/dw per entry, from each row part of the table) -> blend_backward_alpha
    (dL/dalpha per entry; for volume also through the background weight and alpha = 1 - T) ->
    splat_backward. ``absgrad``, when given, receives the per-Gaussian sums of
    the absolute per-pixel dL/dmean2d [N,2] (gsplat's absgrad) whenever means2d gets a gradient.
    The selection is piecewise constant in the geometry and gets no gradient; for the K samplers
    alpha is returned detached (it is the walk's T, over Gaussians the selection does not keep),
    and so it is when the splats need no gradient. ``backward_index``: the selection's
    :class:`~qr_cl.stages.BackwardIndex`, kept by the caller; ``image``: the blend of
    ``features`` already made with the selection (:func:`qr_cl.render.rays.select_and_blend_rays`),
    or None (blended here).
    """

    @staticmethod
    def forward(ctx, means2d: torch.Tensor | None, conics: torch.Tensor | None, opacities: torch.Tensor,
                features: torch.Tensor, background: torch.Tensor | None, selection: Selection,
                absgrad: AbsGradSink | None, backward_index: BackwardIndex, image: torch.Tensor | None):
        image = blend_rays(selection, features, background) if image is None else image
        t_walk = selection.t_walk.get()[:selection.n_rays]
        alpha = torch.from_numpy(1 - t_walk[:, None]).to(image.dtype)
        if selection.sampler != "volume" or not any(ctx.needs_input_grad[:3]):   # alpha is the geometry's
            ctx.mark_non_differentiable(alpha)
        ctx.selection, ctx.absgrad, ctx.backward_index = selection, absgrad, backward_index
        ctx.save_for_backward(features, background)
        return image, alpha

    @staticmethod
    def backward(ctx, grad_image: torch.Tensor, grad_alpha: torch.Tensor):
        sel = ctx.selection
        features, background = ctx.saved_tensors
        splat_grads = [None] * 3
        if any(ctx.needs_input_grad[:3]):
            d_splats = _splat_grads(sel, features, background, grad_image, grad_alpha, ctx.backward_index)
            splat_grads = [_to_tensor(d_splats[:, cols], grad_image) if need else None
                           for cols, need in zip((SPLAT.mean, SPLAT.conic, SPLAT.opacity), ctx.needs_input_grad[:3])]
            if ctx.absgrad is not None and ctx.needs_input_grad[0]:
                ctx.absgrad(d_splats[:, SPLAT.absgrad])
        d_features = weighted_sums(sel, grad_image, features.dtype, ctx.backward_index) \
            if ctx.needs_input_grad[3] else None
        d_background = _background_grad(sel, grad_image) if ctx.needs_input_grad[4] else None
        return (*splat_grads, d_features, d_background, None, None, None, None)


def _splat_grads(sel: Selection, features: torch.Tensor, background: torch.Tensor | None,
                 grad_image: torch.Tensor, grad_alpha: torch.Tensor | None,
                 backward_index: BackwardIndex) -> np.ndarray:
    """dL/dsplats [N,8] float32 on the host (d mean2d, d conic, d opacity and absgrad, the sums of
    |d mean2d x|, |d mean2d y| over the entries, in the slots of :data:`~qr_cl.runtime.SPLAT`) of :class:`RasterFunction`: weight_grads of each
    row part of the table -> blend_backward_alpha -> splat_backward."""
    rt = sel.plan.runtime
    channels = features.shape[1]
    cstride = channel_layout(channels)[2]
    d_trem = None
    if sel.sampler == "volume":            # dL/dT_final: the background weight and alpha = 1 - T
        d_trem = torch.zeros(sel.n_rays, dtype=torch.float64)
        if background is not None:
            d_trem += (grad_image.double() @ background.detach().double())
        if grad_alpha is not None:
            d_trem -= grad_alpha[:, 0].double()
        d_trem = d_trem.numpy()
    table = table_rows(features)
    d_w = device_empty(rt, sel.ids.shape, np.float32)
    with device_rows(rt, host_rows(grad_image), cstride) as dimage:
        for r0, rows in table_parts(rt, table, cstride):
            weight_grads(sel, rows, dimage, channels, row0=r0, out=d_w)
    return splat_backward(sel, blend_backward_alpha(sel, d_w, d_trem), backward_index).get()


class SHColors(torch.autograd.Function):
    """RGB [N,3] = max(SH(dir) . sh + 0.5, 0) of SH coefficients sh [N,(d+1)^2,3] (d <= 3), dir =
    normalize(means [N,3] - campos [3]), by sh.cl on the runtime ``rt``; backward by its
    ``sh_backward`` kernel to sh and means, and to the camera centre campos (minus the sum of the
    means' share, in float64)."""

    @staticmethod
    def forward(ctx, means: torch.Tensor, sh: torch.Tensor, campos: torch.Tensor, rt: Runtime):
        means_dev = to_device(rt, host_rows(means))
        sh_host = np.ascontiguousarray(sh.detach().to("cpu", torch.float32).numpy())
        centre = campos.detach().to("cpu", torch.float32).numpy()
        colors = sh_colors(rt, means_dev, sh_host, centre)
        ctx.stage = (rt, means_dev, sh_host, centre, colors)
        ctx.campos_dtype = campos.dtype
        return torch.from_numpy(colors.get()[:, :3].copy()).to(sh.dtype)

    @staticmethod
    def backward(ctx, grad_rgb: torch.Tensor):
        rt, means_dev, sh_host, centre, colors = ctx.stage
        d_sh, d_means = sh_backward(rt, means_dev, sh_host, centre, colors, host_rows(grad_rgb))
        d_campos = None
        if ctx.needs_input_grad[2]:
            d_campos = torch.from_numpy(-d_means.astype(np.float64).sum(0)).to(ctx.campos_dtype)
        return torch.from_numpy(d_means).to(grad_rgb.dtype), torch.from_numpy(d_sh).to(grad_rgb.dtype), d_campos, None
