"""Sparse 3D convolutions, batch norm and ReLU on :class:`~backbone.sparse.SparseTensor`.

A convolution is, for every kernel offset k: gather the input rows of k's pairs, multiply by the
``[C_in, C_out]`` weight of k, and ``index_add_`` into the output rows. The backward pass is the
same operation on the transposed map with transposed weights (no float atomics, no saved
gathers), sharing each offset's gathered output gradient with the weight gradient, one
``[C_in, P_k] @ [P_k, C_out]`` product per offset.

Weights are stored ``[K, C_in, C_out]`` with offsets ordered like
:func:`~backbone.sparse.kernel_offsets` (dx, dy, dz lexicographic, dz fastest). The equivalent
dense weight is ``weight.reshape(k, k, k, C_in, C_out).permute(4, 3, 0, 1, 2)`` for
``torch.nn.functional.conv3d`` and ``.permute(3, 4, 0, 1, 2)`` for ``conv_transpose3d``.
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from .sparse import KernelMap, SparseTensor


def _apply_map(
    feats: Tensor, weight: Tensor, in_idx: Sequence[Tensor], out_idx: Sequence[Tensor], identity: int | None, n_out: int
) -> Tensor:
    """Sum over offsets k of ``feats[in_idx[k]] @ weight[k]`` added into rows ``out_idx[k]`` of ``[n_out, C_out]``."""
    if identity is not None:
        out = feats @ weight[identity]
    else:
        out = feats.new_zeros(n_out, weight.shape[2])
    for k, (src, dst) in enumerate(zip(in_idx, out_idx)):
        if k == identity or src.numel() == 0:
            continue
        out.index_add_(0, dst, feats.index_select(0, src) @ weight[k])
    return out


class _SparseConvFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, feats: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
        ctx.save_for_backward(feats, weight)
        ctx.kmap = kmap
        return _apply_map(feats, weight, kmap.in_idx, kmap.out_idx, kmap.identity, kmap.n_out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):
        feats, weight = ctx.saved_tensors
        kmap: KernelMap = ctx.kmap
        grad_out = grad_out.contiguous()
        need_feats, need_weight = ctx.needs_input_grad[:2]
        grad_feats = feats.new_zeros(kmap.n_in, feats.shape[1]) if need_feats else None
        grad_weight = torch.zeros_like(weight) if need_weight else None
        for k, (src, dst) in enumerate(zip(kmap.in_idx, kmap.out_idx)):
            if k == kmap.identity:
                if need_feats:
                    grad_feats.add_(grad_out @ weight[k].t())
                if need_weight:
                    torch.mm(feats.t(), grad_out, out=grad_weight[k])
            elif src.numel():
                g = grad_out.index_select(0, dst)
                if need_feats:
                    grad_feats.index_add_(0, src, g @ weight[k].t())
                if need_weight:
                    torch.mm(feats.index_select(0, src).t(), g, out=grad_weight[k])
        return grad_feats, grad_weight, None


def sparse_conv(feats: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
    """Apply a kernel map: feats ``[n_in, C_in]``, weight ``[K, C_in, C_out]`` -> ``[n_out, C_out]``."""
    if feats.dim() != 2 or feats.shape[0] != kmap.n_in:
        raise ValueError(f"feats must have shape [{kmap.n_in}, C_in], got {list(feats.shape)}")
    if weight.dim() != 3 or weight.shape[0] != kmap.volume or weight.shape[1] != feats.shape[1]:
        raise ValueError(
            f"weight must have shape [{kmap.volume}, {feats.shape[1]}, C_out], got {list(weight.shape)}"
        )
    return _SparseConvFunction.apply(feats.contiguous(), weight, kmap)


class _SparseConvBase(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, volume: int, bias: bool) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.weight = nn.Parameter(torch.empty(volume, in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        bound = 1.0 / math.sqrt(volume * in_channels)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def _run(self, x: SparseTensor, kmap: KernelMap) -> Tensor:
        out = sparse_conv(x.feats, self.weight, kmap)
        return out if self.bias is None else out + self.bias

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, offsets={self.weight.shape[0]}, bias={self.bias is not None}"


class SubmanifoldConv3d(_SparseConvBase):
    """Convolution with a centred odd kernel whose output sites are its input sites.

    Input ``[M, C_in]`` at stride s -> output ``[M, C_out]`` at stride s; neighbours are
    ``kernel_size`` voxels of the tensor's stride apart (a dilation of s in finest voxels).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, bias: bool = False) -> None:
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd and >= 1, got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size**3, bias)
        self.kernel_size = kernel_size

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(self._run(x, x.cache.submanifold(x.stride, self.kernel_size)))


class DownsampleConv3d(_SparseConvBase):
    """Kernel-2 stride-2 convolution: stride s -> 2s, one output per occupied parent cell."""

    def __init__(self, in_channels: int, out_channels: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 8, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        kmap = x.cache.downsample(x.stride)
        coarse = 2 * x.stride
        return SparseTensor(x.cache.coords(coarse), self._run(x, kmap), coarse, x.cache)


class UpsampleConv3d(_SparseConvBase):
    """Kernel-2 stride-2 transposed convolution: stride s -> s/2 on the exact finer coordinates.

    The finer coordinates are those that were down-sampled to this tensor's through its cache.
    """

    def __init__(self, in_channels: int, out_channels: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 8, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        kmap = x.cache.upsample(x.stride)
        fine = x.stride // 2
        return SparseTensor(x.cache.coords(fine), self._run(x, kmap), fine, x.cache)


class SparseBatchNorm(nn.BatchNorm1d):
    """BatchNorm over all voxels of a batch (features ``[M, C]``).

    In training mode with fewer than two voxels, where batch statistics do not exist, it normalizes
    with the running statistics and leaves them unchanged.
    """

    def forward(self, x: SparseTensor) -> SparseTensor:
        if self.training and len(x) < 2:
            feats = F.batch_norm(x.feats, self.running_mean, self.running_var, self.weight, self.bias, False, 0.0, self.eps)
        else:
            feats = super().forward(x.feats)
        return x.with_feats(feats)


class SparseReLU(nn.Module):
    """ReLU on the features."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(F.relu(x.feats))


class SparseLinear(nn.Linear):
    """Per-voxel linear map (a 1x1x1 convolution), ``[M, C_in]`` -> ``[M, C_out]``."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(super().forward(x.feats))
