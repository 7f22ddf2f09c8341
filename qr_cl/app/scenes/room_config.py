"""The parameters of a synthetic room (:class:`SyntheticConfig`) and the cache key they make."""
from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass

GENERATOR_VERSION = 6

STYLES = ("flat", "3dgs")

#: SyntheticConfig fields read by the "3dgs" style only (left out of a flat room's cache key).
SPLAT_FIELDS = ("layers", "thickness", "opacity_beta", "floater_opacity_beta", "anisotropy")

#: SyntheticConfig fields read by each feature model only (left out of the other's cache key);
#: the models are described in :mod:`qr_cl.app.scenes.room_features`.
FEATURE_FIELDS = {"clip": ("clip_offset", "clip_noise"), "orthogonal": ("mask_noise", "text_noise")}


@dataclass(frozen=True)
class SyntheticConfig:
    """Parameters of one synthetic room; lengths in metres, image sizes in pixels."""

    seed: int = 0
    n_gaussians: int = 24000
    n_objects: int = 7
    n_wall_objects: int = 3
    n_small_objects: int = 6                       # pillows, books, boxes, TVs and lamps on furniture tops
    n_views: int = 12
    width: int = 160
    height: int = 120
    fov_deg: float = 75.0
    dim: int = 512
    features: str = "clip"                         # "clip": real CLIP anchors; "orthogonal": random prototypes
    clip_offset: float = 0.5                       # clip: norm of the fixed image/text offset
    clip_noise: float = 3.75                       # clip: norm of each mask's noise (about 70 % mask accuracy)
    mask_noise: float = 0.6                        # orthogonal: norm of each mask's noise
    text_noise: float = 0.3                        # orthogonal: norm of each text feature's noise
    floater_fraction: float = 0.01
    points_per_gaussian: int = 16
    room_size: tuple[float, float, float] = (5.0, 4.0, 2.6)
    prototype_seed: int = 12345
    style: str = "flat"
    layers: float = 3.0                            # 3dgs: Gaussians stacked per footprint of a shell
    thickness: float = 0.03                        # 3dgs: shell depth behind each surface, m
    opacity_beta: tuple[float, float] = (0.6, 0.5)           # 3dgs: Beta(a, b) of surface opacities
    floater_opacity_beta: tuple[float, float] = (0.5, 6.0)   # 3dgs: Beta(a, b) of floater opacities
    anisotropy: float = 0.6                        # 3dgs: std of the log of each axis' scale factor

    def __post_init__(self) -> None:
        if self.style not in STYLES:
            raise ValueError(f"style={self.style!r}: choose one of {STYLES}")
        if self.features not in FEATURE_FIELDS:
            raise ValueError(f"features={self.features!r}: choose one of {tuple(FEATURE_FIELDS)}")

    def params(self) -> dict:
        """The parameters the style and the feature model read (a flat room's leave out the
        "3dgs" style's fields; each feature model's leave out the other's)."""
        params = asdict(self)
        unread = [f for model, fields in FEATURE_FIELDS.items() if model != self.features for f in fields]
        if self.style == "flat":
            unread += SPLAT_FIELDS
        for name in unread:
            params.pop(name)
        return params

    def key(self) -> str:
        """A short hash of :meth:`params` and the generator version (the cache folder name)."""
        text = json.dumps({"v": GENERATOR_VERSION, **self.params()}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:12]

    @property
    def folder_name(self) -> str:
        """The scene's folder name in the cache."""
        prefix = "room" if self.style == "flat" else "splat-room"
        return f"{prefix}-{self.seed}-{self.key()}"
