"""Study: the synthetic rooms compared with real captures, the demo's flat rooms and the dense indoor
room, by their opacity histograms and V-Render entries per pixel (Gaussians blended per ray)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ...render import rasterize_plan, select_rays
from ...scene import Camera, Gaussians, orbit_cameras
from ..images import plt
from ..scenes.folders import SceneData
from ..scenes.views import dense_view, real_views
from .plan import Plan


OPACITY_BINS = 20                     # opacity histogram bins over [0, 1]

CONCENTRATION_RAYS = 2048             # hit rays per view whose weight concentration is measured


def volume_selection(gaussians: Gaussians, camera: Camera, pixels: np.ndarray | None = None):
    """V-Render's Selection of ``camera``'s whole image, or of the rays ``pixels`` [P,2] (x, y)."""
    g = gaussians
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, camera.viewmat, camera.K,
                          camera.width, camera.height)
    return select_rays(plan, "volume", 1, pixels)


def entries_per_ray(gaussians: Gaussians, camera: Camera) -> np.ndarray:
    """V-Render's entries (Gaussians blended) of every ray of ``camera``'s image: [H*W] int."""
    sel = volume_selection(gaussians, camera)
    return sel.count.get()[:sel.n_rays]


def weight_concentration(weights: np.ndarray, share: float = 0.9) -> np.ndarray:
    """Per ray of ``weights`` [P,L] (V-Render weights, 0 padded) the fewest Gaussians whose
    weights hold ``share`` of the ray's total weight: [P] int (0 for a ray without weight)."""
    ordered = -np.sort(-weights, axis=1)
    cum = np.cumsum(ordered, axis=1)
    total = cum[:, -1:] if cum.shape[1] else np.zeros((len(weights), 1))
    return np.where(total[:, 0] > 0, (cum < share * total).sum(1) + 1, 0)


def scene_statistics(name: str, kind: str, gaussians: Gaussians, cameras: list[Camera],
                     rng: np.random.Generator) -> dict:
    """Opacity histogram (:data:`OPACITY_BINS` fractions over [0, 1]), V-Render entries per pixel
    over the rays of ``cameras`` that hit anything (mean, median, 90th percentile), and the mean
    number of Gaussians holding 90 % of a ray's weight (:func:`weight_concentration`) over up to
    :data:`CONCENTRATION_RAYS` random hit rays per camera."""
    hist, _ = np.histogram(gaussians.opacities, OPACITY_BINS, (0.0, 1.0))
    counts, holding = [], []
    for cam in cameras:
        c = entries_per_ray(gaussians, cam)
        hit = np.flatnonzero(c > 0)
        rays = np.sort(rng.choice(hit, min(CONCENTRATION_RAYS, len(hit)), replace=False))
        if len(rays):
            pixels = np.stack([rays % cam.width, rays // cam.width], 1).astype(np.int32)
            holding.append(weight_concentration(volume_selection(gaussians, cam, pixels).host()["weights"]))
        counts.append(c)
    counts = np.concatenate(counts)
    hit = counts[counts > 0]
    holding = np.concatenate(holding) if holding else np.zeros(0)
    return {"scene": name, "kind": kind, "n_gaussians": len(gaussians), "views": len(cameras),
            "size": f"{cameras[0].width}x{cameras[0].height}",
            "opacity_hist": (hist / max(len(gaussians), 1)).tolist(),
            "opacity_mean": float(np.mean(gaussians.opacities)),
            "entries_mean": float(hit.mean()) if hit.size else 0.0,
            "entries_median": float(np.median(hit)) if hit.size else 0.0,
            "entries_p90": float(np.percentile(hit, 90)) if hit.size else 0.0,
            "holding_90": float(holding.mean()) if holding.size else 0.0,
            "coverage": float((counts > 0).mean())}


def real_captures(data: Path | None, views: int, size: tuple[int, int]) -> list[tuple[str, Gaussians, list[Camera]]]:
    """(name, Gaussians, ``views`` orbit cameras of ``size`` px) of the real scenes found in ``data``."""
    return [(s.name, s.gaussians, orbit_cameras(s.gaussians.means, views, *size)) for s in real_views(data, *size)]


def compare_scenes(plan: Plan, held: SceneData, flat: SceneData, data: Path | None, seed: int) -> list[dict]:
    """:func:`scene_statistics` of the held-out "3dgs" room, a flat demo room, the real captures of
    ``data`` (orbit views at the plan's RGB size) and the dense indoor room (the >= 50 entries target)."""
    n, rng = plan.stats_views, np.random.default_rng(seed)
    scenes = [(held.name, "synthetic 3dgs room", held.gaussians, [f.camera for f in held.frames[:n]]),
              (flat.name, "synthetic flat room (demo)", flat.gaussians, [f.camera for f in flat.frames[:n]])]
    scenes += [(name, "real capture", g, cams) for name, g, cams in real_captures(data, n, plan.rgb_size)]
    dense = dense_view(plan.dense_gaussians, *plan.rgb_size)
    scenes.append((dense.name, "dense indoor target (procedural)", dense.gaussians, [dense.camera]))
    return [scene_statistics(*scene, rng) for scene in tqdm(scenes, desc="scene statistics", unit="scene")]


def plot_scene_statistics(stats: list[dict], path: Path) -> None:
    """Opacity histograms (left) and mean V-Render entries per pixel (right) of the compared scenes."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8))
    centres = (np.arange(OPACITY_BINS) + 0.5) / OPACITY_BINS
    for s in stats:
        axes[0].plot(centres, s["opacity_hist"], "o-", ms=3, label=f"{s['scene']} ({s['kind']})")
    axes[0].set(xlabel="opacity", ylabel="fraction of Gaussians", title="opacity histograms")
    axes[0].legend(fontsize=6)
    axes[1].barh([s["scene"] for s in stats], [s["entries_mean"] for s in stats])
    axes[1].axvline(50, color="gray", linestyle="--", label="dense indoor target: 50")
    axes[1].set(xlabel="V-Render entries per hit pixel (mean)")
    axes[1].tick_params(axis="y", labelsize=7)
    axes[1].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
