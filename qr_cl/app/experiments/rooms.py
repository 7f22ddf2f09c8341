"""The rooms of a reproduction: the seeded "3dgs" training and held-out rooms, and copies of a room
whose opacities carry Gaussian noise (the paper's perturbation study)."""
from __future__ import annotations

import dataclasses
import zlib
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ...scene import Gaussians, load_ply, save_ply
from ..scenes.room_config import SyntheticConfig
from ..scenes.synthetic import build_folder, room_folder
from .plan import Plan


def splat_rooms(plan: Plan, seed: int, cache: Path | None, features: str = "clip",
                room: dict | None = None) -> tuple[list[Path], Path]:
    """The folders of the plan's "3dgs" training rooms (seeds ``seed`` ...) and its held-out room
    (seed ``seed`` + 1000) of the feature model ``features``, generated on first use; ``room``:
    SyntheticConfig overrides instead of the plan's ``room``."""
    cfgs = [SyntheticConfig(seed=s, style="3dgs", features=features, **(plan.room if room is None else room))
            for s in list(range(seed, seed + plan.train_rooms)) + [seed + 1000]]
    paths = [room_folder(c, cache) for c in tqdm(cfgs, desc="rooms", unit="room")]
    return paths[:-1], paths[-1]


def perturb_opacities(gaussians: Gaussians, scale: float, rng: np.random.Generator) -> Gaussians:
    """``gaussians`` with N(0, ``scale``) noise added to their opacity logits before the sigmoid
    (the paper's perturbation study); opacities are clipped to [1e-6, 1 - 1e-6] before the logit."""
    p = np.clip(np.asarray(gaussians.opacities, np.float64), 1e-6, 1 - 1e-6)
    logit = np.log(p / (1 - p)) + rng.normal(0.0, scale, len(p))
    return dataclasses.replace(gaussians, opacities=(1 / (1 + np.exp(-logit))).astype(np.float32))


def noisy_scene(path: Path, scale: float, seed: int) -> Path:
    """A copy of the scene folder ``path`` (beside it, made once) whose point_cloud.ply has opacity
    noise ``scale`` (:func:`perturb_opacities`, seeded by ``seed`` and the scene's name); the
    other files are symbolic links to the originals."""
    path = Path(path)

    def write(folder: Path) -> None:
        rng = np.random.default_rng([seed, zlib.crc32(path.name.encode()), int(round(scale * 1000))])
        for entry in path.iterdir():
            if entry.name != "point_cloud.ply":
                (folder / entry.name).symlink_to(entry.resolve())
        save_ply(folder / "point_cloud.ply", perturb_opacities(load_ply(path / "point_cloud.ply"), scale, rng))
    return build_folder(path.parent / f"{path.name}-opacity-noise-{scale:g}-{seed}", "point_cloud.ply", write)
