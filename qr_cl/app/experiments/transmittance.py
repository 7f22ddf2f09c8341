"""Study: transmittance profiles along sample rays (the paper's Fig. 3) as each sampler sees them,
and their gaps to V-Render's."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ...render import Selection, rasterize
from ...runtime import SPLAT, SPLAT_FLOATS
from ..images import plot_transmittance_profiles
from ..scenes.folders import SceneData
from .plan import LABELS, Plan
from .scene_statistics import entries_per_ray


PROFILE_RAYS = 256                    # rays whose transmittance profiles are compared with V-Render's

PLOTTED_PROFILES = 3                  # of which this many are plotted (Fig. 3)


def transmittance_profile(selection: Selection, ray: int) -> tuple[np.ndarray, np.ndarray]:
    """Transmittance along ray ``ray`` as its sampler sees it: (depths [n] of the selected
    Gaussians in camera z, T [n+1] before the first and after each selected Gaussian).

    volume: T_i of the full walk; quantile/topk: T^Q among the selected (un-normalized). This is
    what the paper's Fig. 3 plots (see :func:`qr_cl.app.images.plot_transmittance_profiles`).
    """
    h = selection.host()
    n = int(h["count"][ray])
    ids, w = h["ids"][ray, :n], h["weights"][ray, :n].astype(np.float64)
    scale = 1.0 if selection.sampler == "volume" else 1.0 - float(h["t_sel"][ray])
    t = 1.0 - np.concatenate([[0.0], np.cumsum(w * scale)])
    depths = selection.plan.splats.get().reshape(-1, SPLAT_FLOATS)[ids, SPLAT.depth] if n else np.zeros(0, np.float32)
    return depths, t


def step_value(depths: np.ndarray, t: np.ndarray, at: np.ndarray) -> np.ndarray:
    """A transmittance profile (depths [n] ascending, T [n+1]) evaluated at depths ``at`` [m]:
    T after every Gaussian at depth <= ``at``."""
    return t[np.searchsorted(depths, at, side="right")]


def weight_cdf(t: np.ndarray) -> np.ndarray:
    """The normalized cumulative weight (1 - T) / (1 - T_last) [n+1] of a transmittance profile's
    T [n+1]: where along the ray the rendered feature takes its weight (all zeros if T never drops)."""
    mass = 1.0 - t[-1]
    return (1.0 - t) / mass if mass > 0 else np.zeros_like(t)


def profile_gaps(volume: tuple[np.ndarray, np.ndarray], other: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """Two distances of a sampler's profile ``other`` from V-Render's ``volume`` (each (depths [n]
    ascending, T [n+1])), evaluated at the depths of V-Render's entries: mean |T_other - T_volume|,
    and mean |CDF_other - CDF_volume| of their normalized cumulative weights (:func:`weight_cdf`).
    (0, 0) for a ray V-Render does not hit."""
    depths, t = volume
    if not len(depths):
        return 0.0, 0.0
    t_other = step_value(*other, depths)
    cdf_other = step_value(other[0], weight_cdf(other[1]), depths)
    return float(np.mean(np.abs(t_other - t[1:]))), float(np.mean(np.abs(cdf_other - weight_cdf(t)[1:])))


def profile_rays(scene: SceneData, view: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` pixels [n,2] (x, y) drawn among those of ``scene``'s frame ``view`` that V-Render hits."""
    cam = scene.frames[view].camera
    counts = entries_per_ray(scene.gaussians, cam)
    hit = np.flatnonzero(counts > 0)
    pick = np.sort(rng.choice(hit, min(n, len(hit)), replace=False))
    return np.stack([pick % cam.width, pick // cam.width], 1).astype(np.int32)


def transmittance_study(plan: Plan, scene: SceneData, out: Path, seed: int) -> dict:
    """Transmittance profiles of :data:`PROFILE_RAYS` rays of the held-out room's first view for
    V-Render, Q-Render, top-K and Stratified-K at K = ``plan.profile_k``: the mean gaps of each to
    V-Render's profile (:func:`profile_gaps`: transmittance, normalized weight) and the plots of
    three rays (few, median and many entries), written to ``out``."""
    g, cam = scene.gaussians, scene.frames[0].camera
    pixels = profile_rays(scene, 0, PROFILE_RAYS, np.random.default_rng(seed))
    ones = np.ones((len(g), 1), np.float32)
    profiles = {}
    for sampler in ("volume", "quantile", "topk", "stratified"):
        _, _, meta = rasterize(g.means, g.quats, g.scales, g.opacities, ones, cam.viewmat, cam.K, cam.width,
                               cam.height, sampler=sampler, k=plan.profile_k, pixels=pixels)
        name = LABELS[sampler] + ("" if sampler == "volume" else f" K={plan.profile_k}")
        profiles[name] = [transmittance_profile(meta["selection"], r) for r in range(len(pixels))]
    volume = profiles[LABELS["volume"]]
    gaps = {name: np.mean([profile_gaps(v, p) for v, p in zip(volume, rays)], axis=0).tolist()
            for name, rays in profiles.items() if name != LABELS["volume"]}
    entries = np.array([len(v[0]) for v in volume])
    order = np.argsort(entries, kind="stable")
    chosen = [int(order[int(q * (len(order) - 1))]) for q in np.linspace(0.1, 0.95, PLOTTED_PROFILES)]
    files = []
    for r in chosen:
        path = out / f"transmittance_ray{r:03d}.png"
        x, y = pixels[r]
        plot_transmittance_profiles({name: rays[r] for name, rays in profiles.items()}, str(path),
                                    f"pixel ({x}, {y}): {entries[r]} V-Render entries")
        files.append(path.name)
    return {"k": plan.profile_k, "rays": len(pixels), "gap": gaps, "entries_mean": float(entries.mean()),
            "files": files}
