"""Seeded synthetic labelled rooms written in the scene folder format (the embedded default data).

A room (floor, four walls) holds furniture-like objects of ScanNet classes built from open3d
primitives (boxes, cylinders, spheres) and wall-mounted doors, windows, pictures and curtains.
Cameras stand inside the room looking at objects; per-view instance masks are rendered with our
own renderer from the Gaussians' object ids. Two styles of Gaussians (``SyntheticConfig.style``):

- ``"flat"`` (the demo's default): flat Gaussians on the surfaces (thin axis along the normal,
  class colour plus noise, high opacity) and a few low-opacity floaters in the air. A ray meets
  an opaque surface and stops there, so every sampler picks nearly the same Gaussians.
- ``"3dgs"``: rooms that look like optimized 3DGS captures
  (:func:`qr_cl.app.scenes.room_gaussians.splat_gaussians`): every surface is a semi-transparent
  shell ``thickness`` deep holding ``layers`` Gaussians per footprint, with log-normal anisotropic
  scales, random in-plane spins and tilts, Beta-distributed opacities (many faint, many nearly
  opaque, as real captures have) and ``floater_fraction`` of large faint floaters. Rays cross
  tens of Gaussians before V-Render saturates (the comparison with real scenes is in ``qr-cl
  reproduce``'s report). Ground truth: the generator's per-Gaussian labels (no labelled point
  cloud: Gaussians inside a shell are far from any surface point in their own Mahalanobis
  metric, so App. B would drop most of them).

"CLIP" features are SIMULATED from REAL CLIP text embeddings (``SyntheticConfig.features``,
:mod:`qr_cl.app.scenes.room_features`): each class is anchored on the real CLIP ViT-B/32 text
embedding of its name, so classes are as confusable as in CLIP (table and desk, wall and
picture); a mask's feature is its class's anchor plus a fixed image/text offset plus noise
calibrated so that one mask names its own class about 70 % of the time. ``features="orthogonal"``
gives the random-prototype rooms of earlier releases. Real CLIP features plug in through the
same LangSplat files.

Folder written (see :mod:`qr_cl.app.scenes.folders`): point_cloud.ply, cameras.json,
language_features/<frame>_s.npy [4,H,W] + <frame>_f.npy [M,dim], classes.json,
labels/gaussian_labels.npy [N] (class id, -1 for floaters), labels/points.ply (flat style only:
labelled point cloud with a ``label`` vertex property, for the App. B pseudo ground truth).
"""
from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from ...render import rasterize
from ...scene import Camera, Gaussians, save_ply
from ..evaluation.metrics import NYU40_NAMES
from .procedural import concat
from .room_config import GENERATOR_VERSION, SyntheticConfig
from .room_features import RoomFeatures, mask_accuracy
from .room_gaussians import flat_gaussians, splat_gaussians
from .room_layout import room_cameras, room_instances, surface_area

LEVELS = 4            # LangSplat's mask levels (default, s, m, l)


def _instance_maps(gaussians: Gaussians, instance: np.ndarray, n_inst: int, cams: list[Camera]) -> list[np.ndarray]:
    """Per camera an [H,W] int32 map of the dominant instance (-1 where coverage < 0.5)."""
    onehot = np.zeros((len(gaussians), n_inst), np.float32)
    valid = instance >= 0
    onehot[np.flatnonzero(valid), instance[valid]] = 1
    maps = []
    for cam in cams:
        img, _, _ = rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                              onehot, cam.viewmat, cam.K, cam.width, cam.height, sampler="volume")
        img = img.numpy()
        ids = img.argmax(-1).astype(np.int32)
        ids[img.max(-1) < 0.5] = -1
        maps.append(ids)
    return maps


def write_labelled_points(path: Path, points: np.ndarray, labels: np.ndarray) -> None:
    """A binary PLY with float x, y, z and an int ``label`` per vertex (ScanNet-style labelled cloud)."""
    table = np.empty(len(points), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<i4")])
    table["x"], table["y"], table["z"] = points.T
    table["label"] = labels
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\nproperty float x\n"
              "property float y\nproperty float z\nproperty int label\nend_header\n")
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(table.tobytes())


def camera_entry(i: int, cam: Camera) -> dict:
    """The 3DGS cameras.json entry of camera ``i``."""
    r = cam.viewmat[:3, :3].astype(np.float64)
    return {"id": i, "img_name": cam.name, "width": cam.width, "height": cam.height,
            "position": cam.position.tolist(), "rotation": r.T.tolist(), "fx": cam.fx, "fy": cam.fy}


def write_scene(out: Path, cfg: SyntheticConfig) -> None:
    """Generate the room of ``cfg`` into the (existing, empty) folder ``out``."""
    rng = np.random.default_rng(cfg.seed)
    instances = room_instances(cfg, rng)
    areas = np.array([surface_area(m) for _, m in instances])
    n_surface = int(round(cfg.n_gaussians * (1 - cfg.floater_fraction)))
    counts = np.maximum(np.round(n_surface * areas / areas.sum()).astype(int), 16)
    counts[np.argmax(counts)] -= max(int(counts.sum()) - n_surface, 0)    # small objects' minimum: not the floaters'
    spacing = math.sqrt(areas.sum() / counts.sum())          # of the surface Gaussians, m
    points = None
    if cfg.style == "flat":
        parts, inst_ids, points, point_labels = flat_gaussians(cfg, instances, counts, spacing, rng)
    else:
        parts, inst_ids = splat_gaussians(cfg, instances, counts, spacing * math.sqrt(cfg.layers), rng)
    w, d, h = cfg.room_size
    gaussians = concat(parts)
    instance = np.concatenate(inst_ids).astype(np.int64)
    classes = np.array([c for c, _ in instances])
    labels = np.where(instance >= 0, classes[np.maximum(instance, 0)], -1).astype(np.int32)

    save_ply(out / "point_cloud.ply", gaussians)
    centres = np.array([np.mean([np.asarray(m.get_center()) for m in meshes], 0) for _, meshes in instances[5:]])
    footprints = [(c[0], c[1], 0.9, 0.9) for c in centres]
    targets = centres if len(centres) else np.array([[w / 2, d / 2, 1.0]])
    cams = room_cameras(cfg, targets, footprints, rng)
    (out / "cameras.json").write_text(json.dumps([camera_entry(i, c) for i, c in enumerate(cams)], indent=1))

    model = RoomFeatures(cfg)
    text = model.text()
    feat_rng = np.random.default_rng(cfg.seed + 1)
    lang = out / "language_features"
    lang.mkdir()
    all_feats, all_classes = [], []
    for cam, ids in zip(cams, _instance_maps(gaussians, instance, len(instances), cams)):
        present = [i for i in np.unique(ids) if i >= 0 and (ids == i).sum() >= 20]
        rows = np.full(len(instances) + 1, -1, np.int32)
        rows[present] = np.arange(len(present))
        seg = rows[ids]  # ids == -1 maps to rows[-1] == -1
        # LangSplat's layout: LEVELS mask levels, level j's ids offset by j * masks, and a
        # distinct simulated CLIP feature for each level's mask
        segs = np.stack([np.where(seg >= 0, seg + j * len(present), -1) for j in range(LEVELS)])
        mask_classes = np.tile(classes[present], LEVELS) if present else np.zeros(0, np.int64)
        feats = model.masks(mask_classes, feat_rng)
        all_feats.append(feats)
        all_classes.append(mask_classes)
        np.save(lang / f"{cam.name}_s.npy", segs.astype(np.int32))
        np.save(lang / f"{cam.name}_f.npy", feats)

    table = [{"id": c, "name": NYU40_NAMES[c], "text_feature": text[c].tolist()} for c in sorted(NYU40_NAMES)]
    (out / "classes.json").write_text(json.dumps({"feature_dim": cfg.dim, "classes": table}))
    accuracy = mask_accuracy(np.concatenate(all_feats), np.concatenate(all_classes), text)
    (out / "labels").mkdir()
    np.save(out / "labels" / "gaussian_labels.npy", labels)
    if points is not None:
        write_labelled_points(out / "labels" / "points.ply", points, point_labels)
    (out / "synthetic.json").write_text(json.dumps({"generator_version": GENERATOR_VERSION, **cfg.params(),
                                                    "mask_accuracy19": accuracy}, indent=1))


def default_cache() -> Path:
    """``$QR_CL_CACHE/scenes`` or ``~/.cache/qr-cl/scenes``."""
    return Path(os.environ.get("QR_CL_CACHE", Path.home() / ".cache" / "qr-cl")) / "scenes"


def build_folder(target: Path, marker: str, write: Callable[[Path], None]) -> Path:
    """The folder ``target``, made on first use (when ``target / marker`` does not exist) by
    ``write(folder)`` into a temporary folder beside it that is renamed when complete, so a crash
    leaves no half folder and concurrent makers leave one complete folder."""
    if (target / marker).is_file():
        return target
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}-", dir=target.parent))
    try:
        write(tmp)
        try:
            os.replace(tmp, target)
        except OSError:
            if not (target / marker).is_file():
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
    return target


def room_folder(cfg: SyntheticConfig, cache: Path | None = None) -> Path:
    """The folder of the scene ``cfg`` under ``cache`` (default :func:`default_cache`), generated
    on first use (:func:`build_folder`)."""
    cache = Path(cache) if cache is not None else default_cache()
    return build_folder(cache / cfg.folder_name, "synthetic.json", lambda tmp: write_scene(tmp, cfg))
