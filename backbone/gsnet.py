"""GS-Net's 3D network: Gaussians -> voxels -> sparse UNet -> Gaussians -> C-dim unit features."""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from qr_cl.scene import Gaussians
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

    def forward(self, batch: VoxelBatch) -> Tensor:
        """Features ``[N, feature_dim]`` with unit L2 norm, rows in the order of the batch's
        Gaussians."""
        voxels = self._voxel_features(batch)
        if self.reduce == "mean" or batch.one_sample_per_gaussian:
            feats = devoxelize(self.head(voxels), batch, self.reduce)
        else:
            feats = self.head(devoxelize(voxels, batch, self.reduce))
        return F.normalize(feats, dim=1)

    def head_inputs(self, batch: VoxelBatch, rows: Tensor) -> Tensor:
        """Rows ``[U, D + 1]`` (D: the UNet's output channels) of the Gaussians ``rows`` (``[U]``
        int64 indices into the batch's Gaussians) that a renderer can blend in place of their
        features: Gaussian u's row is ``(x_u / |z_u|, 1 / |z_u|)``, x_u its de-voxelized UNet
        feature and z_u = head(x_u) (its feature before normalization), so for any weights
        ``(sum_u w_u row_u) @ head_matrix().T`` is ``sum_u w_u F_u``, F_u = z_u / |z_u| the feature
        :meth:`forward` gives. A blend is linear in the table, so rendering these D + 1 channels
        gives the rays of the [U, feature_dim] table without making it.

        The UNet runs on every voxel (a Gaussian's feature depends on its neighbourhood); the
        de-voxelization and the norms are taken for ``rows`` only. |z_u| = |R (x_u, 1)| with
        :meth:`head_matrix` = QR (Q's columns orthonormal, R [min(feature_dim, D + 1), D + 1]), as
        accurate as forming z_u, without its feature_dim channels; a norm under 1e-12 is taken as
        1e-12, as ``F.normalize`` does."""
        x = devoxelize(self._voxel_features(batch), batch, self.reduce, rows)
        r = torch.linalg.qr(self.head_matrix()).R
        inv = torch.linalg.vector_norm(torch.addmm(r[:, -1], x, r[:, :-1].T), dim=1, keepdim=True)
        inv = inv.clamp_min(1e-12).reciprocal()
        return torch.cat([x * inv, inv], 1)

    def head_matrix(self) -> Tensor:
        """The head as one matrix ``[feature_dim, D + 1]`` on sums of :meth:`head_inputs` rows:
        ``(W | b)``, so that a sum ``(a, s)`` [D + 1] maps to ``W a + s b``."""
        return torch.cat([self.head.weight, self.head.bias[:, None]], 1)

    def _voxel_features(self, batch: VoxelBatch) -> Tensor:
        """The UNet's features ``[M, D]`` of the batch's voxels (checking it was made by :meth:`prepare`)."""
        if not isinstance(batch, VoxelBatch):
            raise TypeError(f"GSNet takes a VoxelBatch (from GSNet.prepare), got {type(batch).__name__}")
        if batch.grid_size != self.voxel_config.grid_size or batch.feats.shape[1] != self.voxel_config.num_features:
            raise ValueError("the VoxelBatch was not made with this network's voxel config: use GSNet.prepare")
        return self.unet(SparseTensor(batch.coords, batch.feats, 1, batch.cache)).feats
