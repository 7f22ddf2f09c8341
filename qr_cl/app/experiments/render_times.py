"""Study: the rendering time of every renderer of the comparison (and of the fused V-Render) on the
held-out room, with 512-D features and whole images."""
from __future__ import annotations

import numpy as np
from tqdm import tqdm

from ..renderers import FeatureRenderer, FusedVolumeRenderer, SamplerRenderer
from ..scenes.folders import SceneData
from ..timing import measure
from .plan import Plan, TrainingRun


def render_times(plan: Plan, scene: SceneData, features: np.ndarray, runs: list[TrainingRun]) -> list[dict]:
    """Wall time (min over ``plan.timing_rounds`` after a warm-up, ms) of rendering ``features``
    [N,C] over the first ``plan.timing_views`` views of ``scene`` at ``plan.timing_size``, per
    renderer of ``runs`` (``rasterize``, whole images) and for the fused V-Render kernel."""
    g = scene.gaussians
    cams = [f.camera.resized(*plan.timing_size) for f in scene.frames[:plan.timing_views]]
    args = (g.means, g.quats, g.scales, g.opacities, features)

    def views_of(renderer: FeatureRenderer):
        def render() -> None:
            for c in cams:
                renderer(*args, c.viewmat, c.K, c.width, c.height)
        return render

    rows = []
    timed = [SamplerRenderer(r.sampler, r.k) for r in runs] + [FusedVolumeRenderer()]
    for renderer in tqdm(timed, desc="render times", unit="renderer"):
        t = measure(views_of(renderer), plan.timing_rounds)
        rows.append({"sampler": renderer.name, "k": renderer.k, "ms": 1e3 * t["min_s"] / len(cams),
                     "median_ms": 1e3 * t["median_s"] / len(cams)})
    return rows
