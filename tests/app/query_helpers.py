"""A small trained GS-Net checkpoint for the query and viewer tests, and how pure a score's top is."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from qr_cl.app.process import torch_threads
from qr_cl.app.training.config import TrainConfig
from qr_cl.app.training.trainer import train

#: Steps of the tiny checkpoint (about 3 s on 2 cores; wall and floor are learnt well by then).
TINY_STEPS = 30


def tiny_checkpoint(room: Path, out: Path, steps: int = TINY_STEPS) -> Path:
    """Train the "tiny" GS-Net on ``room`` for ``steps`` steps into ``out``; the checkpoint's path."""
    with torch_threads(1):
        train(TrainConfig(scenes=[str(room)], out=str(out), steps=steps, views=2, rays=256, net="tiny",
                          grid_size=0.2, checkpoint_every=steps, plateau_interval=4), progress=False)
    return out / "checkpoint.pt"


def top_purity(scores: np.ndarray, labels: np.ndarray, class_id: int, fraction: float | None = None) -> float:
    """The share of ``class_id`` among the Gaussians of highest ``scores`` [N] (``labels`` [N]):
    the top ``fraction`` of all Gaussians, or (None) as many as the class has."""
    count = int(len(scores) * fraction) if fraction is not None else int((labels == class_id).sum())
    top = np.argsort(-scores, kind="stable")[:count]
    return float((labels[top] == class_id).mean())
