"""Pictures of a query: per-Gaussian scores rendered through a K sampler (Q-Render, K = 40 by
default) and coloured into heatmaps over the scene's RGB, and 3DGS PLYs coloured by the score.

The scores are rendered, not the features: for ``cosine`` that is the same image as projecting
the rendered features on the query (blending is linear and the K samplers' weights sum to 1), and
it costs one channel per query instead of C.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib import colormaps

from ...render import rasterize, render_volume_fused
from ...runtime import DEFAULTS
from ...scene import Camera, Gaussians, save_ply

#: The colour map of scores (low = dark blue, high = dark red).
HEATMAP = "turbo"
#: Weight of the heatmap over the grey RGB where the scene is opaque.
OVERLAY_STRENGTH = 0.65


def heat_colours(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Colours [..., 3] float32 in [0, 1] of ``values`` [...] on :data:`HEATMAP`, ``lo`` .. ``hi``
    spanning the map (clipped outside)."""
    t = np.clip((np.asarray(values, np.float64) - lo) / max(hi - lo, 1e-12), 0, 1)
    return colormaps[HEATMAP](t)[..., :3].astype(np.float32)


def render_rgb(gaussians: Gaussians, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(RGB [H,W,3] from the SH colours, V-Render alpha [H,W]) of ``camera``'s view, float32."""
    image, alpha, _ = render_volume_fused(gaussians.means, gaussians.quats, gaussians.scales,
                                          gaussians.opacities, gaussians.sh, camera.viewmat, camera.K,
                                          camera.width, camera.height, sh_degree=gaussians.sh_degree)
    return image.numpy(), alpha.numpy()[..., 0]


def render_values(gaussians: Gaussians, values: np.ndarray, camera: Camera, sampler: str = DEFAULTS.sampler,
                  k: int = DEFAULTS.k) -> tuple[np.ndarray, np.ndarray]:
    """(image [H,W,C], the sampler's alpha [H,W]) of per-Gaussian ``values`` [N,C] rendered
    through ``sampler`` with ``k`` (:func:`qr_cl.rasterize`), float32."""
    image, alpha, _ = rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                np.ascontiguousarray(values, np.float32), camera.viewmat, camera.K,
                                camera.width, camera.height, sampler=sampler, k=k)
    return image.numpy(), alpha.numpy()[..., 0]


def overlay(rgb: np.ndarray, heat: np.ndarray, coverage: np.ndarray) -> np.ndarray:
    """The heatmap colours ``heat`` [H,W,3] laid over a grey copy of ``rgb`` [H,W,3] with weight
    :data:`OVERLAY_STRENGTH` x ``coverage`` [H,W] (V-Render's alpha: no heat over empty space)."""
    grey = np.repeat(np.clip(rgb, 0, 1).mean(-1, keepdims=True), 3, -1)
    w = OVERLAY_STRENGTH * np.clip(coverage, 0, 1)[..., None]
    return ((1 - w) * grey + w * heat).astype(np.float32)


def write_score_ply(path: Path, gaussians: Gaussians, values: np.ndarray, lo: float, hi: float) -> None:
    """An INRIA 3DGS PLY of ``gaussians`` coloured by ``values`` [N] (:func:`heat_colours` over
    ``lo`` .. ``hi``; SH degree 0), for any splat viewer."""
    save_ply(path, Gaussians.from_rgb(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                                      heat_colours(values, lo, hi)))


def write_selection_ply(path: Path, gaussians: Gaussians, selected: np.ndarray) -> None:
    """An INRIA 3DGS PLY of the Gaussians where ``selected`` [N] bool is set, as they are."""
    save_ply(path, gaussians.subset(np.asarray(selected, bool)))
