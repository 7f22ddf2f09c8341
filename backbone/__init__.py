"""GS-Net's 3D network in plain PyTorch: Gaussian voxelization, a sparse voxel UNet, GSNet.

Its input is :class:`qr_cl.scene.Gaussians`, the renderer's Gaussian type.
"""

from .conv import (
    DownsampleConv3d,
    SparseBatchNorm,
    SparseLinear,
    SparseReLU,
    SubmanifoldConv3d,
    UpsampleConv3d,
    conv_threads,
    get_conv_threads,
    set_conv_threads,
    sparse_conv,
)
from .gsnet import GSNet
from .sparse import KernelMap, KernelMapCache, RowBlock, SparseTensor, kernel_offsets, pack_keys, unpack_keys
from .unet import BasicBlock, SparseUNet, UNetConfig, minkunet14, minkunet18
from .voxelize import VoxelBatch, VoxelConfig, devoxelize, voxelize

__all__ = [
    "BasicBlock",
    "DownsampleConv3d",
    "GSNet",
    "KernelMap",
    "KernelMapCache",
    "RowBlock",
    "SparseBatchNorm",
    "SparseLinear",
    "SparseReLU",
    "SparseTensor",
    "SparseUNet",
    "SubmanifoldConv3d",
    "UNetConfig",
    "UpsampleConv3d",
    "VoxelBatch",
    "VoxelConfig",
    "conv_threads",
    "devoxelize",
    "get_conv_threads",
    "kernel_offsets",
    "minkunet14",
    "minkunet18",
    "pack_keys",
    "set_conv_threads",
    "sparse_conv",
    "unpack_keys",
    "voxelize",
]
