"""``qr-cl eval``: 3D open-vocabulary segmentation of Gaussians, mIoU/mAcc tables, images, PLYs.

Prediction per Gaussian: the class (of the evaluated subset) whose text feature has the highest
cosine similarity with the Gaussian's feature. Ground truth: per-Gaussian labels, or (preferred
when present) pseudo labels from a labelled point cloud by paper App. B (:func:`pseudo_labels`).
Gaussians with opacity < 0.1 and labels outside the subset are ignored (NOTES.md protocol).
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from matplotlib import colormaps
from tqdm import tqdm

from ..render import rasterize
from ..scene import Gaussians, quat_to_rotmat
from ..stages.select import ray_entries, select
from .data import ClassTable, SceneData, load_scene_folder
from .images import save_rgb
from .loss import view_plan
from .metrics import NYU40_NAMES, SUBSETS, miou_macc
from .model import build_net, torch_threads

MIN_OPACITY = 0.1


def pseudo_labels(gaussians: Gaussians, points: np.ndarray, labels: np.ndarray, k: int = 5,
                  max_mahalanobis: float = 0.1, min_opacity: float = MIN_OPACITY) -> np.ndarray:
    """Per-Gaussian labels [N] int64 from a labelled point cloud (paper App. B); -1 = no label.

    points [P,3] (scene units), labels [P]. For each Gaussian: its ``k`` nearest points (open3d
    KD-tree, Euclidean), majority label (ties go to the nearer point). Dropped (-1): opacity <
    ``min_opacity``, or every neighbour farther than ``max_mahalanobis`` in the Gaussian's own
    Mahalanobis distance sqrt(d^T Sigma^-1 d), Sigma = R S^2 R^T.
    """
    n = len(gaussians)
    if len(points) == 0:
        return np.full(n, -1, np.int64)
    import open3d as o3d  # function-local: open3d takes ~0.9 s to import and only the pseudo labels need it
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    tree = o3d.geometry.KDTreeFlann(cloud)
    k = min(k, len(points))
    idx = np.empty((n, k), np.int64)
    for i, m in enumerate(np.asarray(gaussians.means, np.float64)):
        idx[i] = np.asarray(tree.search_knn_vector_3d(m, k)[1])
    d = np.asarray(points)[idx] - gaussians.means[:, None, :].astype(np.float64)          # [N,k,3]
    rot = quat_to_rotmat(gaussians.quats.astype(np.float64))                               # [N,3,3]
    local = np.einsum("nji,nkj->nki", rot, d) / np.maximum(gaussians.scales[:, None, :], 1e-12)
    maha = np.linalg.norm(local, axis=2)                                                   # [N,k]
    lab = np.asarray(labels, np.int64)[idx]
    votes = (lab[:, :, None] == lab[:, None, :]).sum(2)
    out = lab[np.arange(n), votes.argmax(1)]
    out[(maha > max_mahalanobis).all(1) | (gaussians.opacities < min_opacity)] = -1
    return out


def ground_truth(scene: SceneData, source: str = "auto", k: int = 5, max_mahalanobis: float = 0.1) -> tuple[np.ndarray, str]:
    """(labels [N] int64 with -1 = ignored, the source used). ``source``: "points" (App. B from
    labels/points.ply), "gaussians" (labels/gaussian_labels.npy) or "auto" (points when present)."""
    if source not in ("auto", "points", "gaussians"):
        raise ValueError(f"ground truth source {source!r}: choose auto, points or gaussians")
    if source in ("auto", "points") and scene.points is not None:
        return pseudo_labels(scene.gaussians, scene.points, scene.point_labels, k, max_mahalanobis), "points"
    if source in ("auto", "gaussians") and scene.gaussian_labels is not None:
        labels = scene.gaussian_labels.copy()
        labels[scene.gaussians.opacities < MIN_OPACITY] = -1
        return labels, "gaussians"
    raise ValueError(f"{scene.root}: no ground truth for source={source!r} (labels/points.ply or "
                     "labels/gaussian_labels.npy)")


def reached_gaussians(scene: SceneData, sampler: str = "quantile", k: int = 40) -> np.ndarray:
    """[N] bool: the Gaussians that ``sampler``'s selection (``k``) of some pixel of some view of
    ``scene`` holds, i.e. those its training rays can reach. A per-scene model (the free-feature
    baseline) learns only these; GS-Net predicts every Gaussian from its neighbourhood."""
    reached = np.zeros(len(scene.gaussians), bool)
    for view in range(len(scene.frames)):
        sel = select(view_plan(scene, view), sampler, k)
        reached[sel.ids.get()[ray_entries(*sel.spans())]] = True
    return reached


def predict(features: np.ndarray, classes: ClassTable) -> np.ndarray:
    """Class id [N] of the text feature most cosine-similar to each row of ``features`` [N,C]."""
    f = features / np.maximum(np.linalg.norm(features, axis=1, keepdims=True), 1e-12)
    return classes.ids[(f @ classes.text_features.T).argmax(1)]


def evaluate_features(scene: SceneData, features: np.ndarray, gt: np.ndarray, subsets=(19, 15, 10)) -> dict:
    """mIoU/mAcc of per-Gaussian ``features`` [N,C] against ``gt`` [N] for each class subset:
    {subset: {"miou", "macc", "per_class", "n_evaluated", "classes_present"}}."""
    if scene.classes is None:
        raise ValueError(f"{scene.root}: classes.json is needed for open-vocabulary evaluation")
    if features.shape != (len(scene.gaussians), scene.classes.text_features.shape[1]):
        raise ValueError(f"features have shape {features.shape}, expected "
                         f"({len(scene.gaussians)}, {scene.classes.text_features.shape[1]})")
    results = {}
    for size in subsets:
        table = scene.classes.subset(SUBSETS[size])
        res = miou_macc(predict(features, table), gt, table.ids)
        res["classes_present"] = len(res["per_class"])
        results[int(size)] = res
    return results


def network_features(checkpoint: Path | dict, scene: SceneData) -> np.ndarray:
    """GS-Net features [N,C] (eval mode) of ``scene`` from a training checkpoint."""
    ckpt = torch.load(checkpoint, weights_only=False) if not isinstance(checkpoint, dict) else checkpoint
    cfg = ckpt["config"]
    net = build_net(cfg["net"], cfg["feature_dim"], cfg["grid_size"])
    net.load_state_dict(ckpt["model"])
    net.eval()
    with torch.no_grad():
        return net(net.prepare([scene.gaussians])).numpy()


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
        rgb = _render(scene, np.maximum(g.sh[:, 0] * 0.28209479177387814 + 0.5, 0), v, "volume")
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


def markdown_table(rows: list[dict], subsets=(19, 15, 10)) -> str:
    """A markdown table of ``rows`` ({"method", "scene", "split", subset: {"miou", "macc"}}), values in %."""
    head = "| method | scene | split | " + " | ".join(f"mIoU{s} | mAcc{s}" for s in subsets) + " |\n"
    head += "| --- | --- | --- | " + " | ".join("---: | ---:" for _ in subsets) + " |\n"
    body = ""
    for r in rows:
        cells = []
        for s in subsets:
            m = r["metrics"][s]
            cells += [f"{100 * m['miou']:.1f}" if not math.isnan(m["miou"]) else "-",
                      f"{100 * m['macc']:.1f}" if not math.isnan(m["macc"]) else "-"]
        body += f"| {r['method']} | {r['scene']} | {r['split']} | " + " | ".join(cells) + " |\n"
    return head + body


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``qr-cl eval``."""
    parser.add_argument("scenes", nargs="+", help="scene folders with classes.json and ground truth")
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", help="GS-Net checkpoint.pt from qr-cl train")
    src.add_argument("--features", help="per-Gaussian features .npy [N,C] (one scene)")
    parser.add_argument("--out", required=True, help="output folder (results.json, results.md, images/)")
    parser.add_argument("--gt", choices=("auto", "points", "gaussians"), default="auto",
                        help="ground truth: App. B from labels/points.ply, labels/gaussian_labels.npy, or auto")
    parser.add_argument("--knn", type=int, default=5, help="App. B neighbours (default 5)")
    parser.add_argument("--max-mahalanobis", type=float, default=0.1, help="App. B distance cut (default 0.1)")
    parser.add_argument("--views", type=int, nargs="*", default=[0], help="frames to render images of (default 0)")
    parser.add_argument("--level", type=int, default=0, help="LangSplat mask level (default 0)")


def run(args: argparse.Namespace) -> int:
    """Evaluate every scene, write results.json / results.md and the images; print the table."""

    if args.features and len(args.scenes) != 1:
        raise SystemExit("qr-cl eval: --features evaluates exactly one scene")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt = torch.load(args.checkpoint, weights_only=False) if args.checkpoint else None
    rows = []
    for path in tqdm(args.scenes, desc="eval", unit="scene"):
        scene = load_scene_folder(path, args.level)
        with torch_threads(1):
            feats = network_features(ckpt, scene) if ckpt is not None else np.load(args.features).astype(np.float32)
        gt, source = ground_truth(scene, args.gt, args.knn, args.max_mahalanobis)
        metrics = evaluate_features(scene, feats, gt)
        with torch_threads(1):
            write_visuals(scene, feats, gt, out / "images", args.views)
        rows.append({"method": "GS-Net" if ckpt is not None else Path(args.features).name, "scene": scene.name,
                     "split": "-", "gt": source, "metrics": metrics})
    means = {s: {k: float(np.nanmean([r["metrics"][s][k] for r in rows])) for k in ("miou", "macc")}
             for s in (19, 15, 10)}
    rows_md = rows + ([{"method": rows[0]["method"], "scene": "mean", "split": "-", "metrics": means}]
                      if len(rows) > 1 else [])
    (out / "results.json").write_text(json.dumps({"scenes": rows, "mean": means}, indent=1))
    text = markdown_table(rows_md)
    (out / "results.md").write_text(text)
    print(text + f"\nresults: {out.resolve() / 'results.md'} (and results.json, images/)")
    return 0
