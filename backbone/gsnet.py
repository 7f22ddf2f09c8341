"""GS-Net's 3D network: Gaussians -> voxels -> sparse UNet -> Gaussians -> C-dim unit features."""

from __future__ import annotations

from functools import partial
from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from qr_cl.runtime import host_empty
from qr_cl.scene import Gaussians
from .conv import SPLIT, run_tasks
from .sparse import SparseTensor
from .unet import SparseUNet, UNetConfig, minkunet14
from .voxelize import Reduce, VoxelBatch, VoxelConfig, devoxelize, voxelize


class GSNet(nn.Module):
    """Predict one L2-normalized ``feature_dim`` vector per Gaussian.

    ``voxelize -> SparseUNet -> de-voxelize (max or mean) -> linear head -> L2-normalize``.
    The head is applied per voxel before de-voxelizing when that gives the same result (``mean``
    reduction, or one sample per Gaussian), which is cheaper when voxels are fewer than Gaussians.

    ``unet_config`` defaults to MinkUNet14 with ``voxel_config.num_features`` input channels.
    """

    def __init__(
        self,
        feature_dim: int = 512,
        voxel_config: VoxelConfig = VoxelConfig(),
        unet_config: UNetConfig | None = None,
        reduce: Reduce = "max",
    ) -> None:
        super().__init__()
        if feature_dim < 1:
            raise ValueError(f"feature_dim must be >= 1, got {feature_dim}")
        if reduce not in ("max", "mean"):
            raise ValueError(f"reduce must be 'max' or 'mean', got {reduce!r}")
        unet_config = unet_config if unet_config is not None else minkunet14(voxel_config.num_features)
        if unet_config.in_channels != voxel_config.num_features:
            raise ValueError(
                f"unet_config.in_channels is {unet_config.in_channels} but the voxel config "
                f"makes {voxel_config.num_features} features"
            )
        self.feature_dim = feature_dim
        self.voxel_config = voxel_config
        self.reduce = reduce
        self.unet = SparseUNet(unet_config)
        self.head = nn.Linear(unet_config.out_channels, feature_dim)

    def prepare(self, scenes: Gaussians | Sequence[Gaussians]) -> VoxelBatch:
        """Voxelize one scene's or several scenes' Gaussians (numpy or torch storage) with this
        network's voxel config.

        The result depends on the (frozen) Gaussians only: keep it across training steps, and its
        kernel maps, built by the first forward, are reused.
        """
        return voxelize(scenes, self.voxel_config)

    def forward(self, batch: VoxelBatch, rows: Tensor | None = None) -> Tensor:
        """Features ``[N, feature_dim]`` with unit L2 norm, rows in the order of the batch's
        Gaussians; with ``rows`` (``[U]`` int64 indices into them) only those Gaussians' features,
        ``[U, feature_dim]``, in the order of ``rows``.

        The UNet always runs on every voxel (a Gaussian's feature depends on its neighbourhood);
        ``rows`` limits the de-voxelization, head and normalization (and their backward) to the
        Gaussians a training step renders.
        """
        if not isinstance(batch, VoxelBatch):
            raise TypeError(f"GSNet takes a VoxelBatch (from GSNet.prepare), got {type(batch).__name__}")
        if batch.grid_size != self.voxel_config.grid_size or batch.feats.shape[1] != self.voxel_config.num_features:
            raise ValueError("the VoxelBatch was not made with this network's voxel config: use GSNet.prepare")
        voxels = self.unet(SparseTensor(batch.coords, batch.feats, 1, batch.cache)).feats
        if rows is not None:
            return unit_linear(devoxelize(voxels, batch, self.reduce, rows), self.head.weight, self.head.bias)
        if self.reduce == "mean" or batch.one_sample_per_gaussian:
            feats = devoxelize(self.head(voxels), batch, self.reduce)
        else:
            feats = self.head(devoxelize(voxels, batch, self.reduce))
        return F.normalize(feats, dim=1)


#: Rows per block of :func:`unit_linear`'s backward row dot products (a small reused temporary).
_BLOCK_ROWS = 1024
#: Rows from which :func:`unit_linear` runs as :data:`~backbone.conv.SPLIT` row blocks on the
#: convolution threads (fixed: the weight gradient's summation order depends on the blocks).
MIN_SPLIT_ROWS = 4096


def _pooled(rows: int, cols: int) -> Tensor:
    """An uninitialised float32 [rows, cols] tensor over pooled host memory (memory of an earlier
    one that nothing references any more: no fresh pages to fault in)."""
    return torch.from_numpy(host_empty((rows, cols)))


def _row_blocks(rows: int) -> list[slice]:
    """The row blocks :func:`unit_linear` runs as: :data:`~backbone.conv.SPLIT` about equal ones
    from :data:`MIN_SPLIT_ROWS` rows, else one (a function of the row count only)."""
    n = SPLIT if rows >= MIN_SPLIT_ROWS else 1
    bounds = [rows * i // n for i in range(n + 1)]
    return [slice(a, b) for a, b in zip(bounds[:-1], bounds[1:])]


class _UnitLinear(torch.autograd.Function):
    """y = normalize(x @ weight.T + bias) row by row, with y and the gradient of the linear output
    in pooled host memory, and the backward's row dot products taken in blocks: no [U, C]
    temporaries are allocated per call (torch's normalize backward allocates several). Large
    inputs run as row blocks on the convolution threads (:func:`~backbone.conv.run_tasks`); rows
    are independent, and the weight and bias gradients add the blocks' parts in block order, so
    results do not depend on the thread count."""

    @staticmethod
    def forward(ctx, x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
        y = _pooled(x.shape[0], weight.shape[0])
        inv = torch.empty(x.shape[0], 1)

        def rows(b: slice) -> None:
            torch.addmm(bias, x[b], weight.t(), out=y[b])
            torch.linalg.vector_norm(y[b], dim=1, keepdim=True, out=inv[b])
            inv[b].clamp_min_(1e-12).reciprocal_()
            y[b].mul_(inv[b])

        run_tasks([partial(rows, b) for b in _row_blocks(x.shape[0])])
        ctx.save_for_backward(x, weight, y, inv)
        return y

    @staticmethod
    def backward(ctx, grad: Tensor):
        x, weight, y, inv = ctx.saved_tensors
        grad = grad.contiguous()
        dz = _pooled(*y.shape)                        # dz = (g - y (y . g)) / |z|
        dx = torch.empty_like(x)
        blocks = _row_blocks(y.shape[0])
        parts: list[tuple[Tensor, Tensor] | None] = [None] * len(blocks)

        def rows(i: int, b: slice) -> None:
            for start in range(b.start, b.stop, _BLOCK_ROWS):
                sub = slice(start, min(start + _BLOCK_ROWS, b.stop))
                torch.mul(grad[sub], y[sub], out=dz[sub])
                dot = dz[sub].sum(1, keepdim=True)
                torch.mul(y[sub], dot, out=dz[sub])
            torch.sub(grad[b], dz[b], out=dz[b])
            dz[b].mul_(inv[b])
            torch.mm(dz[b], weight, out=dx[b])
            parts[i] = (dz[b].t() @ x[b], dz[b].sum(0))

        run_tasks([partial(rows, i, b) for i, b in enumerate(blocks)])
        dweight, dbias = parts[0]
        for dw, db in parts[1:]:
            dweight, dbias = dweight + dw, dbias + db
        return dx, dweight, dbias


def unit_linear(x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
    """``F.normalize(F.linear(x, weight, bias), dim=1)`` (x [U, C_in], weight [C, C_in], bias [C]
    -> [U, C] unit rows, float32; a row whose linear output is zero stays zero) without
    allocating [U, C] temporaries in forward or backward: GS-Net's head on a step's rows."""
    return _UnitLinear.apply(x.contiguous(), weight, bias)

