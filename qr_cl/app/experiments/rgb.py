"""Study: RGB fidelity from SH colours, PSNR of Q-Render (raw, times V-Render's alpha, times its own
alpha) and of top-K against V-Render, with pictures."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ...render import rasterize
from ...scene import Camera, Gaussians
from ..images import save_image_grid
from ..scenes.folders import SceneData
from .plan import Plan
from .scene_statistics import real_captures


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two images with values clipped to [0, 1] (peak 1)."""
    mse = float(np.mean((np.clip(a, 0, 1) - np.clip(b, 0, 1)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1 / mse)


def rgb_renders(g: Gaussians, cam: Camera, ks: tuple[int, ...]) -> dict:
    """V-Render's RGB [H,W,3] and alpha [H,W,1] from SH, and per K the normalized RGB [H,W,3] and
    own alpha [H,W,1] (1 - T where the walk stopped) of Q-Render ("quantile") and top-K ("topk")."""
    args = (g.means, g.quats, g.scales, g.opacities, g.sh, cam.viewmat, cam.K, cam.width, cam.height)
    rgb, alpha, _ = rasterize(*args, sampler="volume", sh_degree=g.sh_degree)
    renders = {"volume": rgb.numpy(), "alpha": alpha.numpy()}
    for sampler in ("quantile", "topk"):
        renders[sampler] = {}
        for k in ks:
            k_rgb, k_alpha, _ = rasterize(*args, sampler=sampler, k=k, sh_degree=g.sh_degree)
            renders[sampler][k] = (k_rgb.numpy(), k_alpha.numpy())
    return renders


def rgb_fidelity(name: str, g: Gaussians, cams: list[Camera], ks: tuple[int, ...], out: Path) -> list[dict]:
    """PSNR (mean over ``cams``) against V-Render at each K of Q-Render's raw normalized image, of
    its colour times V-Render's alpha and times its own alpha, and of top-K's colour times
    V-Render's alpha; writes rgb_<name>.png of the first view (V-Render | raw Q-Render |
    Q-Render x V alpha | 4 |V - raw Q|, at the largest K)."""
    renders = [rgb_renders(g, c, ks) for c in cams]

    def mean_psnr(sampler: str, k: int, composite) -> float:
        return float(np.mean([psnr(composite(*r[sampler][k], r["alpha"]), r["volume"]) for r in renders]))
    rows = [{"scene": name, "k": k, "views": len(cams), "size": f"{cams[0].width}x{cams[0].height}",
             "psnr_raw": mean_psnr("quantile", k, lambda q, own, v_alpha: q),
             "psnr_alpha": mean_psnr("quantile", k, lambda q, own, v_alpha: q * v_alpha),
             "psnr_own_alpha": mean_psnr("quantile", k, lambda q, own, v_alpha: q * own),
             "psnr_topk_alpha": mean_psnr("topk", k, lambda q, own, v_alpha: q * v_alpha)} for k in ks]
    first, k = renders[0], max(ks)
    q = first["quantile"][k][0]
    panels = [first["volume"], q, q * first["alpha"], 4 * np.abs(np.clip(q, 0, 1) - np.clip(first["volume"], 0, 1))]
    save_image_grid(out / f"rgb_{name}.png", [panels], ["V-Render", f"Q-Render K={k} (raw, normalized)",
                                                        f"Q-Render K={k} x V-Render alpha", "4 |V - raw Q|"])
    return rows


def rgb_study(plan: Plan, held: SceneData, data: Path | None, out: Path) -> list[dict]:
    """:func:`rgb_fidelity` on the held-out room's first views (resized to the plan's RGB size) and
    on orbit views of the real captures of ``data`` (none when absent)."""
    scenes = [(held.name, held.gaussians, [f.camera.resized(*plan.rgb_size) for f in held.frames[:plan.rgb_views]])]
    scenes += real_captures(data, plan.rgb_views, plan.rgb_size)
    rows = []
    for name, g, cams in tqdm(scenes, desc="RGB fidelity", unit="scene"):
        rows += rgb_fidelity(name, g, cams, plan.rgb_ks, out)
    return rows
