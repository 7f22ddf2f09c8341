"""GS-Net as the application builds it: the UNet presets, the network, and its features of a scene
from a training checkpoint.

The network takes a scene's Gaussians as they are (``net.prepare([scene.gaussians])``)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from qr_cl.backbone import GSNet, VoxelConfig, minkunet14
from ..scenes.folders import SceneData

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


class CheckpointError(ValueError):
    """A file that is not a usable qr-cl training checkpoint; the message names the file and why."""


#: What every training checkpoint holds.
CHECKPOINT_KEYS = ("config", "model")


def load_checkpoint(path: Path | str) -> dict:
    """The training checkpoint at ``path`` (a dict with :data:`CHECKPOINT_KEYS`); CheckpointError
    naming the file when it is missing, unreadable or not a qr-cl checkpoint."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        ckpt = torch.load(path, weights_only=False)
    except Exception as exc:                            # torch raises many kinds for a foreign file
        raise CheckpointError(f"{path}: not a torch checkpoint ({type(exc).__name__}: {exc})") from exc
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(ckpt, dict) or k not in ckpt]
    if missing:
        raise CheckpointError(f"{path}: not a qr-cl training checkpoint (no {', '.join(missing)})")
    return ckpt


def network_features(checkpoint: Path | dict, scene: SceneData, dtype: np.dtype | type = np.float32) -> np.ndarray:
    """GS-Net features [N,C] (eval mode) of ``scene`` from a training checkpoint (a path, or the
    dict :func:`load_checkpoint` returns), in ``dtype``: float16 keeps a table for rendering in
    half the memory (the renderers read it as half and blend in float32)."""
    ckpt = checkpoint if isinstance(checkpoint, dict) else load_checkpoint(checkpoint)
    cfg = ckpt["config"]
    net = build_net(cfg["net"], cfg["feature_dim"], cfg["grid_size"])
    net.load_state_dict(ckpt["model"])
    net.eval()
    with torch.no_grad():
        return net(net.prepare([scene.gaussians])).numpy().astype(dtype, copy=False)
