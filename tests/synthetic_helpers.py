"""Tiny synthetic scenes shared by the training/evaluation tests (generated once per session)."""
from __future__ import annotations

from pathlib import Path

from qr_cl.app.scenes.room_config import SyntheticConfig
from qr_cl.app.scenes.synthetic import room_folder


def tiny_config(seed: int = 0, **overrides) -> SyntheticConfig:
    """A small room: 3000 Gaussians, 4 views of 64x48, 32-D orthogonal-prototype features (the
    calibrated CLIP model needs 512 channels; tests of it build their own rooms)."""
    base = dict(seed=seed, n_gaussians=3000, n_objects=4, n_wall_objects=2, n_views=4, width=64,
                height=48, dim=32, points_per_gaussian=8, features="orthogonal")
    base.update(overrides)
    return SyntheticConfig(**base)


def tiny_scene(cache: Path, seed: int = 0, **overrides) -> Path:
    """The folder of :func:`tiny_config` under ``cache`` (generated on first use)."""
    return room_folder(tiny_config(seed, **overrides), cache)
