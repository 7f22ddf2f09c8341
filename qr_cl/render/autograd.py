"""torch autograd through the blend: gradients w.r.t. per-Gaussian features (and background).

The Gaussians are frozen in GS-Net, so the Selection (geometry) is a constant of the graph:
no gradient flows to means, quats, scales or opacities.
"""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import torch

from ..runtime import channel_layout, check_buffer, check_channels, padded_rows
from ..stages.blend import blend_backward, blend_forward
from ..stages.select import Selection


def _rows(rt, tensor: torch.Tensor, cstride: int) -> cla.Array:
    """A device copy of a [R, C] tensor as float32 rows of cstride floats."""
    check_buffer(rt, 4 * tensor.shape[0] * cstride, f"{tensor.shape[0]} rows x {cstride} channels")
    return cla.to_device(rt.queue, padded_rows(tensor.detach().cpu().numpy(), cstride))


class BlendFunction(torch.autograd.Function):
    """image [P,C] = blend(selection, features [N,C]) (+ t_rem * background [C]).

    forward copies features into a device buffer, runs blend.cl and copies the image back;
    backward copies dImage in and runs the deterministic transposed gather for dF. The
    background gets its gradient sum_p t_rem[p] dImage[p]. The selection gets none.
    """

    @staticmethod
    def forward(ctx, features: torch.Tensor, selection: Selection, background: torch.Tensor | None):
        rt = selection.plan.runtime
        channels = features.shape[1]
        cstride = channel_layout(channels)[2]
        bg = None if background is None else background.detach().cpu().numpy()
        image = blend_forward(selection, _rows(rt, features, cstride), channels, bg)
        ctx.selection, ctx.channels = selection, channels
        out = image.get()[:, :channels]
        return torch.from_numpy(np.ascontiguousarray(out)).to(features.dtype)

    @staticmethod
    def backward(ctx, grad_image: torch.Tensor):
        sel, channels = ctx.selection, ctx.channels
        rt = sel.plan.runtime
        cstride = channel_layout(channels)[2]
        d_features = d_background = None
        if ctx.needs_input_grad[0]:
            d = blend_backward(sel, _rows(rt, grad_image, cstride), channels).get()[:, :channels]
            d_features = torch.from_numpy(np.ascontiguousarray(d)).to(grad_image.dtype)
        if ctx.needs_input_grad[2]:
            t_rem = torch.from_numpy(sel.t_rem.get()[:sel.n_rays]).to(grad_image.dtype)
            d_background = t_rem @ grad_image
        return d_features, None, d_background


def blend(selection: Selection, features: torch.Tensor, background: torch.Tensor | None = None) -> torch.Tensor:
    """Differentiable blend: features [N,C] float tensor (C in 1..2048) -> image [P,C] (rays of the
    selection; for the whole image row p = y * width + x). Computed in float32 on the device and
    returned in features' dtype. Gradients flow to features and background only."""
    if features.ndim != 2 or features.shape[0] != selection.n_gaussians:
        raise ValueError(f"features must be [{selection.n_gaussians}, C], got {tuple(features.shape)}")
    check_channels(features.shape[1])
    if background is not None and tuple(background.shape) != (features.shape[1],):
        raise ValueError(f"background must be [{features.shape[1]}], got {tuple(background.shape)}")
    return BlendFunction.apply(features, selection, background)
