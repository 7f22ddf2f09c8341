"""The feature renderers that the experiments and the benchmarks compare, as objects: ``rasterize``
through a sampler with its K, and the fused V-Render (``render_volume_fused``), a renderer of its
own without a selection. Both are called with the Gaussians, the features and a camera."""
from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Union

import numpy as np

from ..render import rasterize, render_volume_fused

#: The name under which reports list the fused V-Render (beside the samplers' names).
FUSED_NAME = "volume_fused"


@dataclass(frozen=True)
class SamplerRenderer:
    """``rasterize`` through ``sampler`` with K = ``k`` (0 for V-Render, which has none)."""

    sampler: str
    k: int = 0

    @property
    def name(self) -> str:
        return self.sampler

    def __call__(self, means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
                 features, viewmat: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple:
        """(image [H,W,C], alpha [H,W,1], meta) of ``features`` [N,C] (see :func:`qr_cl.rasterize`)."""
        return rasterize(means, quats, scales, opacities, features, viewmat, K, width, height,
                         sampler=self.sampler, k=self.k or 1)


@dataclass(frozen=True)
class FusedVolumeRenderer:
    """The fused V-Render kernel (``render_volume_fused``): V-Render's image without a selection."""

    name: ClassVar[str] = FUSED_NAME
    k: ClassVar[int] = 0

    def __call__(self, means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
                 features, viewmat: np.ndarray, K: np.ndarray, width: int, height: int) -> tuple:
        """(image [H,W,C], alpha [H,W,1], meta) of ``features`` [N,C] (see :func:`qr_cl.render_volume_fused`)."""
        return render_volume_fused(means, quats, scales, opacities, features, viewmat, K, width, height)


FeatureRenderer = Union[SamplerRenderer, FusedVolumeRenderer]
