"""A MinkUNet-style sparse voxel UNet built from :mod:`backbone.conv`.

Plan (D = number of levels): a stem convolution at stride 1; D encoder stages, each a kernel-2
stride-2 down-sampling (conv, BN, ReLU) then residual blocks; D decoder stages, each a kernel-2
stride-2 transposed convolution (conv, BN, ReLU) back to the finer coordinates, concatenation with
the encoder output of that stride (the stem's at stride 1), then residual blocks. The output is
the last decoder stage's features at the input voxels.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import nn

from .conv import (
    DownsampleConv3d,
    SparseBatchNorm,
    SparseLinear,
    SparseReLU,
    SubmanifoldConv3d,
    UpsampleConv3d,
)
from .sparse import SparseTensor


@dataclass(frozen=True)
class UNetConfig:
    """Channel and block plan of :class:`SparseUNet`.

    ``enc_channels[i]`` / ``enc_blocks[i]``: width and residual blocks at stride ``2^(i+1)``;
    ``dec_channels[i]`` / ``dec_blocks[i]``: decoder stage i, coarsest first, at stride
    ``2^(D-1-i)``. ``stem_kernel`` is the stem's kernel size (MinkUNet uses 5).
    """

    in_channels: int
    stem_channels: int = 32
    stem_kernel: int = 5
    enc_channels: tuple[int, ...] = (32, 64, 128, 256)
    enc_blocks: tuple[int, ...] = (1, 1, 1, 1)
    dec_channels: tuple[int, ...] = (256, 128, 96, 96)
    dec_blocks: tuple[int, ...] = (1, 1, 1, 1)
    bn_momentum: float = 0.1

    def __post_init__(self) -> None:
        depth = len(self.enc_channels)
        if depth < 1:
            raise ValueError("enc_channels must name at least one level")
        for name in ("enc_blocks", "dec_channels", "dec_blocks"):
            if len(getattr(self, name)) != depth:
                raise ValueError(f"{name} must have {depth} entries like enc_channels, got {len(getattr(self, name))}")
        if self.in_channels < 1 or self.stem_channels < 1:
            raise ValueError("in_channels and stem_channels must be >= 1")
        if min(self.enc_channels + self.dec_channels) < 1 or min(self.enc_blocks + self.dec_blocks) < 1:
            raise ValueError("channels and block counts must be >= 1")

    @property
    def depth(self) -> int:
        """Number of stride-2 levels."""
        return len(self.enc_channels)

    @property
    def out_channels(self) -> int:
        """Channels of the UNet's output."""
        return self.dec_channels[-1]


def minkunet14(in_channels: int, **overrides) -> UNetConfig:
    """MinkUNet14 plan: widths 32-32-64-128-256 | 256-128-96-96, one block per stage."""
    return replace(UNetConfig(in_channels), **overrides)


def minkunet18(in_channels: int, **overrides) -> UNetConfig:
    """MinkUNet18 plan: MinkUNet14's widths with two blocks per stage."""
    return replace(UNetConfig(in_channels, enc_blocks=(2, 2, 2, 2), dec_blocks=(2, 2, 2, 2)), **overrides)


class ConvBNReLU(nn.Sequential):
    """A sparse convolution module followed by BatchNorm and ReLU."""

    def __init__(self, conv: nn.Module, channels: int, momentum: float) -> None:
        super().__init__(conv, SparseBatchNorm(channels, momentum=momentum), SparseReLU())


class BasicBlock(nn.Module):
    """Residual block: (3^3 conv, BN, ReLU, 3^3 conv, BN) + shortcut, then ReLU.

    The shortcut is a per-voxel linear map + BN when the channel count changes.
    """

    def __init__(self, in_channels: int, out_channels: int, momentum: float) -> None:
        super().__init__()
        self.conv1 = SubmanifoldConv3d(in_channels, out_channels, 3)
        self.bn1 = SparseBatchNorm(out_channels, momentum=momentum)
        self.conv2 = SubmanifoldConv3d(out_channels, out_channels, 3)
        self.bn2 = SparseBatchNorm(out_channels, momentum=momentum)
        self.relu = SparseReLU()
        self.shortcut = (
            nn.Sequential(SparseLinear(in_channels, out_channels, bias=False), SparseBatchNorm(out_channels, momentum=momentum))
            if in_channels != out_channels
            else nn.Identity()
        )

    def forward(self, x: SparseTensor) -> SparseTensor:
        y = self.bn2(self.conv2(self.relu(self.bn1(self.conv1(x)))))
        return self.relu(y.with_feats(y.feats + self.shortcut(x).feats))


def _blocks(in_channels: int, out_channels: int, count: int, momentum: float) -> nn.Sequential:
    widths = [in_channels] + [out_channels] * count
    return nn.Sequential(*(BasicBlock(a, b, momentum) for a, b in zip(widths[:-1], widths[1:])))


class SparseUNet(nn.Module):
    """Sparse UNet: SparseTensor ``[M, in_channels]`` at stride 1 -> ``[M, out_channels]`` at the same voxels.

    Scenes in one batch (the coordinates' batch index) never exchange information, except
    through BatchNorm statistics in training mode.
    """

    def __init__(self, config: UNetConfig) -> None:
        super().__init__()
        self.config = config
        mom = config.bn_momentum
        self.stem = ConvBNReLU(
            SubmanifoldConv3d(config.in_channels, config.stem_channels, config.stem_kernel), config.stem_channels, mom
        )
        self.down = nn.ModuleList()
        self.enc = nn.ModuleList()
        width = config.stem_channels
        skips = [width]
        for ch, n in zip(config.enc_channels, config.enc_blocks):
            self.down.append(ConvBNReLU(DownsampleConv3d(width, width), width, mom))
            self.enc.append(_blocks(width, ch, n, mom))
            width = ch
            skips.append(width)
        skips.pop()
        self.up = nn.ModuleList()
        self.dec = nn.ModuleList()
        for ch, n in zip(config.dec_channels, config.dec_blocks):
            skip = skips.pop()
            self.up.append(ConvBNReLU(UpsampleConv3d(width, ch), ch, mom))
            self.dec.append(_blocks(ch + skip, ch, n, mom))
            width = ch

    @property
    def out_channels(self) -> int:
        """Channels of the output features."""
        return self.config.out_channels

    def forward(self, x: SparseTensor) -> SparseTensor:
        if x.stride != 1:
            raise ValueError(f"SparseUNet expects a stride-1 input, got stride {x.stride}")
        if x.feats.shape[1] != self.config.in_channels:
            raise ValueError(f"expected {self.config.in_channels} input channels, got {x.feats.shape[1]}")
        if not bool(torch.isfinite(x.feats).all()):
            raise ValueError("SparseUNet input feats contain NaN or infinite values")
        x = self.stem(x)
        skips = [x]
        for down, enc in zip(self.down, self.enc):
            x = enc(down(x))
            skips.append(x)
        skips.pop()
        for up, dec in zip(self.up, self.dec):
            x = up(x)
            x = dec(x.with_feats(torch.cat([x.feats, skips.pop().feats], 1)))
        return x
