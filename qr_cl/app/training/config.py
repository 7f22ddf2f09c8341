"""The options of a training run (:class:`TrainConfig`), checked when made."""
from __future__ import annotations

from dataclasses import dataclass, field

from ...runtime import DEFAULTS, SAMPLERS
from .network import NETS


@dataclass
class TrainConfig:
    """Training options (lengths in scene units, counts per step)."""

    scenes: list[str]
    out: str
    steps: int = 200
    batch_scenes: int = 1
    views: int = 4
    rays: int = 2048
    sampler: str = DEFAULTS.sampler
    k: int = DEFAULTS.k
    lr: float = 1e-2                    # chosen by experiment on the 3dgs rooms (docs/design.md, "GS-Net's defaults")
    temperature: float = 0.1
    grid_size: float = 0.1
    net: str = "small"
    seed: int = 0
    checkpoint_every: int = 50
    plateau_interval: int = 25
    patience: int = 2
    level: int = 0
    view_selections_mb: int = 1024      # whole-view selections kept (MiB; results do not depend on it)
    feature_dim: int = field(default=0)

    def __post_init__(self) -> None:
        if self.sampler not in SAMPLERS:
            raise ValueError(f"sampler={self.sampler!r}: choose one of {SAMPLERS}")
        if self.net not in NETS:
            raise ValueError(f"net={self.net!r}: choose one of {sorted(NETS)}")
        if not self.scenes:
            raise ValueError("no training scenes given")
