"""Pictures of a segmentation: per view RGB | PCA of the rendered features | predicted classes |
ground truth, a coloured and labelled PLY of the Gaussians, and the colour legend."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from matplotlib import colormaps

from ...render import rasterize
from ...runtime import SH_C0
from ...scene import Gaussians
from ..images import save_rgb
from ..scenes.folders import SceneData
from .metrics import NYU40_NAMES, SUBSETS
from .scoring import predict


def _palette(ids) -> dict[int, np.ndarray]:
    cmap = colormaps["tab20"]
    return {int(c): np.asarray(cmap(i % 20)[:3], np.float32) for i, c in enumerate(sorted(ids))}


def _render(scene: SceneData, values: np.ndarray, view: int, sampler: str = "quantile",
            visible: np.ndarray | None = None) -> np.ndarray:
    """Full image [H,W,C] of per-Gaussian ``values`` [N,C] from frame ``view`` (only the
    Gaussians where ``visible`` [N] bool is set, if given)."""
    g, cam = scene.gaussians, scene.frames[view].camera
    opacities = g.opacities if visible is None else np.where(visible, g.opacities, 0).astype(np.float32)
    img, _, _ = rasterize(g.means, g.quats, g.scales, opacities, np.ascontiguousarray(values, np.float32),
                          cam.viewmat, cam.K, cam.width, cam.height, sampler=sampler, k=40)
    return img.numpy()


def pca_rgb(image: np.ndarray) -> np.ndarray:
    """[H,W,C] feature map -> [H,W,3] in [0,1]: its 3 principal components, 1..99 % stretched."""
    flat = torch.from_numpy(image.reshape(-1, image.shape[-1]).astype(np.float64))
    centred = flat - flat.mean(0)
    sample = centred[:: max(1, len(flat) // 2048)]
    _, vecs = torch.linalg.eigh(sample.T @ sample)  # torch: numpy's LAPACK threads crawl on busy cores
    proj = (centred @ vecs.flip(1)[:, :3]).numpy()
    lo, hi = np.percentile(proj, 1, axis=0), np.percentile(proj, 99, axis=0)
    return np.clip((proj - lo) / np.maximum(hi - lo, 1e-12), 0, 1).reshape(*image.shape[:2], 3)


def write_coloured_ply(path: Path, gaussians: Gaussians, colours: np.ndarray, pred: np.ndarray, gt: np.ndarray) -> None:
    """A binary PLY of the Gaussian centres with uchar red/green/blue and int ``label`` (predicted)
    and ``gt`` properties (open3d reads points and colours)."""
    table = np.empty(len(gaussians), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"),
                                       ("blue", "u1"), ("label", "<i4"), ("gt", "<i4")])
    table["x"], table["y"], table["z"] = gaussians.means.T
    rgb = np.round(np.clip(colours, 0, 1) * 255).astype(np.uint8)
    table["red"], table["green"], table["blue"] = rgb.T
    table["label"], table["gt"] = pred, gt
    props = "".join(f"property {t} {n}\n" for n, t in (("x", "float"), ("y", "float"), ("z", "float"),
                    ("red", "uchar"), ("green", "uchar"), ("blue", "uchar"), ("label", "int"), ("gt", "int")))
    with open(path, "wb") as fh:
        fh.write(f"ply\nformat binary_little_endian 1.0\nelement vertex {len(table)}\n{props}end_header\n".encode())
        fh.write(table.tobytes())


def write_visuals(scene: SceneData, features: np.ndarray, gt: np.ndarray, out: Path, views=(0,), subset: int = 19) -> list[Path]:
    """Per view a PNG [RGB | PCA of the rendered features | predicted classes | ground truth (only
    the labelled Gaussians drawn)], and a
    coloured, labelled PLY of the Gaussians (predicted colours). Returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    table = scene.classes.subset(SUBSETS[subset])
    pred = predict(features, table)
    palette = _palette(table.ids)
    pred_rgb = np.stack([palette[int(c)] for c in pred])
    gt_rgb = np.stack([palette.get(int(c), np.zeros(3, np.float32)) for c in gt])
    files = []
    for v in views:
        g = scene.gaussians
        rgb = _render(scene, np.maximum(g.sh[:, 0] * SH_C0 + 0.5, 0), v, "volume")
        panels = [rgb, pca_rgb(_render(scene, features, v)), _render(scene, pred_rgb, v, "volume"),
                  _render(scene, gt_rgb, v, "volume", np.isin(gt, table.ids))]
        path = out / f"{scene.name}_view{v:03d}.png"
        save_rgb(path, np.concatenate(panels, axis=1))
        files.append(path)
    ply = out / f"{scene.name}_segmentation.ply"
    write_coloured_ply(ply, scene.gaussians, pred_rgb, pred, gt)
    legend = out / "legend.md"
    legend.write_text("| class | colour |\n| --- | --- |\n" + "".join(
        f"| {NYU40_NAMES.get(int(c), c)} | #{''.join(f'{int(round(x * 255)):02x}' for x in palette[int(c)])} |\n"
        for c in table.ids))
    return files + [ply, legend]
