"""The scene a query or the viewer asks: its Gaussians, cameras and classes, and its per-Gaussian
features from a GS-Net checkpoint or a file.

A scene is a scene folder (:mod:`qr_cl.app.scenes.folders`; language features are not needed) or
a bare ``.ply``/``.splat`` file (no cameras, no classes). Feature files: ``.npy`` [N, C], or a
PLY whose vertices carry numbered properties ``feature_0..`` (also ``feat_`` or
``language_feature_``), one row per Gaussian of the scene.
"""
from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...scene import Camera, Gaussians, load_cameras, load_scene, read_ply_vertices, scene_camera_file
from ..process import torch_threads
from ..scenes.folders import NO_LANGUAGE, ClassTable, SceneData, SceneDataError, load_scene_folder
from ..training.network import load_checkpoint, network_features

#: Numbered vertex properties of a feature PLY: <prefix>_<channel>.
FEATURE_PROPERTY = re.compile(r"^(feature|feat|language_feature)_(\d+)$")


@dataclass
class QueryScene:
    """A scene to ask: ``gaussians`` (N), its ``cameras`` (empty when it has none), ``classes``
    (its classes.json, or None) and the folder's :class:`SceneData` (None for a bare file)."""

    name: str
    gaussians: Gaussians
    cameras: list[Camera]
    classes: ClassTable | None
    data: SceneData | None


def load_query_scene(path: str | Path, level: int = 0) -> QueryScene:
    """The scene at ``path`` (module docstring): a folder's Gaussians (point_cloud.ply or
    SceneSplat's files), cameras (cameras.json or transforms, when present) and classes.json (when
    present), or a ``.ply``/``.splat`` file."""
    path = Path(path)
    if path.is_file():
        g = load_scene(path)
        return QueryScene(path.stem, g, [], None, SceneData(path, g, [], None, None, None, None))
    if not path.exists():
        raise FileNotFoundError(2, "no such scene folder or file", str(path))
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", f".*{NO_LANGUAGE}")  # frames without language features are fine here
        data = load_scene_folder(path, level, require_language=False)
    camera_file = scene_camera_file(path, required=False)
    cameras = load_cameras(camera_file) if camera_file else []
    return QueryScene(path.name, data.gaussians, cameras, data.classes, data)


def read_features(path: str | Path, n: int) -> np.ndarray:
    """Per-Gaussian features [n, C] float32 from ``path`` (.npy, or a PLY with numbered feature
    properties, module docstring); SceneDataError naming the file when it has another shape."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(2, "no such features file (--features)", str(path))
    if path.suffix.lower() == ".ply":
        columns, _ = read_ply_vertices(path)
        numbered = sorted((int(m.group(2)), name) for name in columns if (m := FEATURE_PROPERTY.match(name)))
        if not numbered:
            raise SceneDataError(f"{path}: no feature_<i> (or feat_<i>, language_feature_<i>) vertex properties")
        feats = np.stack([np.asarray(columns[name], np.float32) for _, name in numbered], 1)
    else:
        try:
            feats = np.load(path, allow_pickle=False)
        except (ValueError, OSError) as exc:
            raise SceneDataError(f"{path}: not a readable .npy array ({exc})") from None
    if feats.ndim != 2 or feats.shape[0] != n or not np.issubdtype(feats.dtype, np.number):
        raise SceneDataError(f"{path}: features of shape {feats.shape} ({feats.dtype}); the scene has {n} "
                             "Gaussians, so [N, C] numbers are expected")
    feats = feats.astype(np.float32)
    if not np.all(np.isfinite(feats)):
        raise SceneDataError(f"{path}: features contain NaN or infinite values")
    return feats


def scene_features(scene: QueryScene, checkpoint: str | Path | None = None,
                   features: str | Path | None = None) -> np.ndarray | None:
    """The per-Gaussian features [N, C] float32 of ``scene``: GS-Net's from a training
    ``checkpoint`` (CheckpointError when it is not one), or read from a ``features`` file; None
    when neither is given."""
    if checkpoint is not None:
        ckpt = load_checkpoint(checkpoint)
        with torch_threads(1):
            return network_features(ckpt, scene.data).astype(np.float32)
    if features is not None:
        return read_features(features, len(scene.gaussians))
    return None
