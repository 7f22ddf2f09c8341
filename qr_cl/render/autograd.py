"""torch autograd through the blend: gradients w.r.t. per-Gaussian features (and background).

The Gaussians are frozen in GS-Net, so the Selection (geometry) is a constant of the graph:
no gradient flows to means, quats, scales or opacities.
"""
from __future__ import annotations

import torch

from ..runtime import channel_layout, check_channels, device_rows, host_empty, shared_array
from ..stages.blend import blend_backward, blend_forward
from ..stages.select import Selection


def _host_rows(tensor: torch.Tensor):
    """A numpy view of a [R, C] tensor's rows (float32 on the CPU; converted only otherwise)."""
    return tensor.detach().to("cpu", torch.float32).numpy()


def _output(rows: int, channels: int, cstride: int):
    """A pooled host array [rows, cstride] the kernels write into, and the [rows, channels]
    tensor over it that the caller receives (a strided view when channels < cstride)."""
    host = host_empty((rows, cstride))
    return host, torch.from_numpy(host if cstride == channels else host[:, :channels])


class BlendFunction(torch.autograd.Function):
    """image [P,C] = blend(selection, features [N,C]) (+ t_rem * background [C]).

    No copies where the memory allows it: forward reads the features in place (float32,
    C-contiguous, C == cstride; else padded once into a pooled host array) and writes the image
    straight into the memory of the tensor it returns (a pooled host array that no earlier
    output still uses; [P, cstride] with a [P, C] view returned when C < cstride); backward
    likewise reads dImage in place and writes dF straight into the returned gradient. On devices
    that do not share host memory the same calls copy through pooled device buffers. The
    backward is the deterministic transposed gather; the background gets its gradient
    sum_p t_rem[p] dImage[p]. The selection gets none.
    """

    @staticmethod
    def forward(ctx, features: torch.Tensor, selection: Selection, background: torch.Tensor | None):
        rt = selection.plan.runtime
        channels = features.shape[1]
        cstride = channel_layout(channels)[2]
        bg = None if background is None else background.detach().cpu().numpy()
        host, image = _output(selection.n_rays, channels, cstride)
        with device_rows(rt, _host_rows(features), cstride) as rows, shared_array(rt, host, "w") as out:
            blend_forward(selection, rows, channels, bg, out=out)
        ctx.selection, ctx.channels = selection, channels
        return image.to(features.dtype)

    @staticmethod
    def backward(ctx, grad_image: torch.Tensor):
        sel, channels = ctx.selection, ctx.channels
        rt = sel.plan.runtime
        cstride = channel_layout(channels)[2]
        d_features = d_background = None
        if ctx.needs_input_grad[0]:
            host, d = _output(sel.n_gaussians, channels, cstride)
            with device_rows(rt, _host_rows(grad_image), cstride) as dimage, shared_array(rt, host, "w") as out:
                blend_backward(sel, dimage, channels, out=out)
            d_features = d.to(grad_image.dtype)
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
