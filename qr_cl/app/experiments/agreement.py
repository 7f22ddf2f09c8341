"""Study: how differently the renderers supervise the same network: each renderer's feature image
compared with V-Render's (cosine similarity)."""
from __future__ import annotations

import numpy as np

from ...render import rasterize
from ..renderers import SamplerRenderer
from ..scenes.folders import SceneData
from .plan import Plan, TrainingRun


def feature_agreement(plan: Plan, scene: SceneData, features: np.ndarray, runs: list[TrainingRun]) -> list[dict]:
    """Mean cosine similarity between each renderer's feature image of ``features`` [N,C] and
    V-Render's, over the pixels of ``scene``'s first view (at ``plan.timing_size``) where
    V-Render's alpha is >= 0.5: how differently the renderers supervise the same network."""
    g, cam = scene.gaussians, scene.frames[0].camera.resized(*plan.timing_size)
    args = (g.means, g.quats, g.scales, g.opacities, features, cam.viewmat, cam.K, cam.width, cam.height)
    ref, alpha, _ = rasterize(*args, sampler="volume")
    covered = alpha.numpy()[..., 0] >= 0.5
    ref = ref.numpy()[covered]
    rows = []
    for run in runs:
        img = SamplerRenderer(run.sampler, run.k)(*args)[0].numpy()[covered]
        cos = np.sum(img * ref, 1) / np.maximum(np.linalg.norm(img, axis=1) * np.linalg.norm(ref, axis=1), 1e-12)
        rows.append({"sampler": run.sampler, "k": run.k, "cosine": float(cos.mean()) if cos.size else float("nan")})
    return rows
