"""Pictures of a segmentation: per camera one figure of RGB | PCA of the rendered features |
predicted classes | ground truth | relevancy of one text query, with titles and a legend naming
the classes predicted or labelled in the scene; a coloured and labelled PLY of the Gaussians; the colour legend as markdown;
and figures of several models' predictions side by side (:func:`write_comparison`).

The relevancy panel is the cosine similarity between the Q-Render (K=40) feature image and the
query's text feature (from the scene's classes.json), shown with the turbo colour map stretched
over the picture's 2nd..98th percentiles (so it shows where, not how much)."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from matplotlib import colormaps

from ...render import rasterize
from ...runtime import DEFAULTS, SH_C0
from ...scene import Camera, Gaussians, orbit_cameras
from ..images import plt
from ..scenes.folders import ClassTable, SceneData, unit_rows
from .metrics import NYU40_NAMES, SUBSETS, UNLABELLED
from .scoring import predict

#: The smallest panel of a picture, pixels (width, height).
PANEL_SIZE = (320, 240)

#: The colour of Gaussians predicted as no class (no feature): white, which tab20 (the classes'
#: palette) does not use; its greys name classes.
UNLABELLED_RGB = np.ones(3, np.float32)


def _palette(ids) -> dict[int, np.ndarray]:
    cmap = colormaps["tab20"]
    return {int(c): np.asarray(cmap(i % 20)[:3], np.float32) for i, c in enumerate(sorted(ids))}


def _render(scene: SceneData, values: np.ndarray, cam: Camera, sampler: str = DEFAULTS.sampler,
            visible: np.ndarray | None = None) -> np.ndarray:
    """Full image [H,W,C] of per-Gaussian ``values`` [N,C] seen by ``cam`` (only the Gaussians
    where ``visible`` [N] bool is set, if given)."""
    g = scene.gaussians
    opacities = g.opacities if visible is None else np.where(visible, g.opacities, 0).astype(np.float32)
    img, _, _ = rasterize(g.means, g.quats, g.scales, opacities, np.ascontiguousarray(values, np.float32),
                          cam.viewmat, cam.K, cam.width, cam.height, sampler=sampler, k=DEFAULTS.k)
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


def frame_cameras(scene: SceneData, views: Sequence[int]) -> list[Camera]:
    """The cameras of the scene's frames ``views`` (indices; those it has), enlarged to at least
    :data:`PANEL_SIZE`; an orbit camera when it has no frames."""
    cams = [scene.frames[v].camera for v in views if v < len(scene.frames)] if scene.frames else \
        orbit_cameras(scene.gaussians.means, 1, *PANEL_SIZE)
    return [c if c.width >= PANEL_SIZE[0] else c.resized(PANEL_SIZE[0], round(c.height * PANEL_SIZE[0] / c.width))
            for c in cams]


def default_query(table: ClassTable, gt: np.ndarray) -> str:
    """The name of the class of ``table`` other than wall and floor with the most Gaussians in
    ``gt`` [N] (wall if there is none)."""
    ids = [int(c) for c in table.ids if int(c) not in (1, 2)]
    counts = [(int((gt == c).sum()), c) for c in ids]
    best = max(counts, default=(0, 1))
    return table.names[list(table.ids).index(best[1])] if best[0] else table.names[0]


def _figure(path: Path, panels: list[tuple[str, np.ndarray]], legend: list[tuple[str, np.ndarray]]) -> None:
    """One PNG: the ``panels`` (title, image [H,W,3] in [0,1]) side by side at their pixel size,
    titled, and rows of legend patches (name, colour [3]) under them."""
    h, w = panels[0][1].shape[:2]
    title_px, legend_px = 26, 30 * (1 + (len(legend) - 1) // 8) if legend else 0
    dpi = 100
    fig = plt.figure(figsize=(len(panels) * w / dpi, (h + title_px + legend_px) / dpi), dpi=dpi)
    total = h + title_px + legend_px
    for i, (title, image) in enumerate(panels):
        ax = fig.add_axes((i / len(panels), legend_px / total, 1 / len(panels), h / total))
        ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
        ax.set_axis_off()
        ax.set_title(title, fontsize=11)
    if legend:
        handles = [plt.Rectangle((0, 0), 1, 1, facecolor=colour, edgecolor="0.4", linewidth=0.5) for _, colour in legend]
        fig.legend(handles, [name for name, _ in legend], loc="lower center", ncol=min(len(legend), 8),
                   fontsize=10, frameon=False)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)


def write_visuals(scene: SceneData, features: np.ndarray, gt: np.ndarray, out: Path, cameras: list[Camera],
                  query: str | None = None, subset: int = 19) -> list[Path]:
    """Per camera a figure (module docstring) of per-Gaussian ``features`` [N,C] against ``gt``
    [N] (only the labelled Gaussians drawn in the ground truth) with the relevancy of ``query``
    (a class name of the scene's classes.json; default :func:`default_query`), and a coloured,
    labelled PLY of the Gaussians (predicted colours). Returns the files written."""
    out.mkdir(parents=True, exist_ok=True)
    table = scene.classes.subset(SUBSETS[subset])
    query = query or default_query(table, gt)
    if query not in scene.classes.names:
        raise KeyError(f"{scene.root}: query {query!r} is not a class of classes.json")
    text = scene.classes.text_features[scene.classes.names.index(query)]
    pred = predict(features, table)
    palette = _palette(table.ids)
    pred_rgb = np.stack([palette.get(int(c), UNLABELLED_RGB) for c in pred])
    gt_rgb = np.stack([palette.get(int(c), np.zeros(3, np.float32)) for c in gt])
    labelled = np.isin(gt, table.ids)
    legend = [(name, palette[int(c)]) for c, name in zip(table.ids, table.names) if (pred == c).any() or (gt == c).any()]
    legend += [("no feature", UNLABELLED_RGB)] if (pred == UNLABELLED).any() else []
    g = scene.gaussians
    files = []
    for i, cam in enumerate(cameras):
        feature_image = _render(scene, features, cam)
        hit = np.linalg.norm(feature_image, axis=-1) > 0
        cosine = unit_rows(feature_image) @ text
        lo, hi = np.percentile(cosine[hit], (2, 98)) if hit.any() else (0.0, 1.0)
        relevancy = colormaps["turbo"](np.clip((cosine - lo) / max(hi - lo, 1e-12), 0, 1))[..., :3]
        pred_image = _render(scene, pred_rgb, cam, "volume")
        gt_image = _render(scene, gt_rgb, cam, "volume", labelled)
        panels = [("RGB", _render(scene, np.maximum(g.sh[:, 0] * SH_C0 + 0.5, 0), cam, "volume")),
                  ("feature PCA", pca_rgb(feature_image)), ("prediction", pred_image),
                  ("ground truth", gt_image), (f'relevancy "{query}"', relevancy)]
        path = out / f"{scene.name}_{Path(cam.name).stem or f'camera{i}'}.png"
        _figure(path, panels, legend)
        files.append(path)
    ply = out / f"{scene.name}_segmentation.ply"
    write_coloured_ply(ply, scene.gaussians, pred_rgb, pred, gt)
    legend_md = out / "legend.md"
    legend_md.write_text("| class | colour |\n| --- | --- |\n" + "".join(
        f"| {NYU40_NAMES.get(int(c), c)} | #{''.join(f'{int(round(x * 255)):02x}' for x in palette[int(c)])} |\n"
        for c in table.ids))
    return files + [ply, legend_md]


def write_comparison(scene: SceneData, models: dict[str, np.ndarray], gt: np.ndarray, out: Path,
                     cameras: list[Camera], subset: int = 19) -> list[Path]:
    """Per camera one figure of the predicted classes of several models side by side: RGB | each
    model's prediction (``models``: title -> per-Gaussian features [N,C]; white: Gaussians without a
    feature) | ground truth (labelled Gaussians only), with one legend. Returns the PNGs written
    (``out``/<scene>_<camera>_compared.png)."""
    out.mkdir(parents=True, exist_ok=True)
    table = scene.classes.subset(SUBSETS[subset])
    palette = _palette(table.ids)
    preds = {name: predict(features, table) for name, features in models.items()}
    shown = np.concatenate([*preds.values(), gt])
    legend = [(name, palette[int(c)]) for c, name in zip(table.ids, table.names) if (shown == c).any()]
    legend += [("no feature", UNLABELLED_RGB)] if (shown == UNLABELLED).any() else []
    gt_rgb = np.stack([palette.get(int(c), np.zeros(3, np.float32)) for c in gt])
    g = scene.gaussians
    files = []
    for i, cam in enumerate(cameras):
        panels = [("RGB", _render(scene, np.maximum(g.sh[:, 0] * SH_C0 + 0.5, 0), cam, "volume"))]
        panels += [(name, _render(scene, np.stack([palette.get(int(c), UNLABELLED_RGB) for c in pred]), cam, "volume"))
                   for name, pred in preds.items()]
        panels.append(("ground truth", _render(scene, gt_rgb, cam, "volume", np.isin(gt, table.ids))))
        path = out / f"{scene.name}_{Path(cam.name).stem or f'camera{i}'}_compared.png"
        _figure(path, panels, legend)
        files.append(path)
    return files
