"""GS-Net as the application builds it: UNet presets, the network, and its threads.

The network takes a scene's Gaussians as they are (``net.prepare([scene.gaussians])``)."""
from __future__ import annotations

from contextlib import contextmanager

import torch

from ..backbone import GSNet, VoxelConfig, minkunet14

#: UNet presets: name -> overrides of backbone.minkunet14 (empty = MinkUNet14 itself).
NETS: dict[str, dict] = {
    "tiny": dict(stem_channels=8, stem_kernel=3, enc_channels=(8, 16, 16, 16), dec_channels=(16, 16, 16, 16)),
    "small": dict(stem_channels=16, enc_channels=(16, 32, 64, 64), dec_channels=(64, 64, 48, 48)),
    "mink14": {},
}


def build_net(net: str, feature_dim: int, grid_size: float):
    """A GSNet with the UNet preset ``net`` (see :data:`NETS`) predicting ``feature_dim``-D features."""
    voxels = VoxelConfig(grid_size=grid_size)
    return GSNet(feature_dim, voxels, minkunet14(voxels.num_features, **NETS[net]))


@contextmanager
def torch_threads(n: int):
    """Run the block with ``n`` torch intra-op threads (restored after). One thread is the default
    for training: PoCL renders with its own threads, and torch's OpenMP workers spin badly when the
    cores are shared (a 0.7 s step took 60 s with 2 threads on a busy 2-core machine)."""
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)
