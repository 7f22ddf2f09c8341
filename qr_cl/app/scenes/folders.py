"""Scene folders: Gaussians, cameras, LangSplat language features, classes and ground truth.

Layout (real and synthetic scenes alike)::

    scene/
      point_cloud.ply                 INRIA 3DGS PLY, or SceneSplat's coord.npy, color.npy, ...
                                      (:mod:`qr_cl.scene.scenesplat`, docs/scenesplat.md)
      cameras.json                    3DGS cameras (img_name names the frame), or
                                      transforms_train.json / transforms.json (file_path names it)
      language_features/<img>_s.npy   [L,H,W] (or [H,W]) mask ids per pixel, -1 = none (LangSplat:
                                      L = 4 levels default/small/medium/large, level j's ids
                                      offset by the mask counts of the levels before it)
      language_features/<img>_f.npy   [M,C] float mask features of all levels (rows indexed by
                                      the ids); a frame keeps the chosen level's rows only, so
                                      the other levels' masks never become negatives
      classes.json                    optional {"classes": [{"id", "name", "text_feature": [C]}]}
      labels/gaussian_labels.npy      optional [N] int class id per Gaussian (-1 = unlabelled)
      labels/points.ply               optional labelled point cloud (x, y, z, int ``label``)
      segment20.npy, instance.npy     a SceneSplat folder's labels (:mod:`.label_spaces`) and
                                      instance ids (-1 = none)

A SceneSplat folder without camera files has no frames (rendering, evaluation and queries need
none; training says it needs them).

:func:`load_scene_folder` validates all of it and raises :class:`SceneDataError` naming the file,
the frame and the problem.
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...scene import (Camera, Gaussians, SceneFormatError, SceneSplatFolder, is_scenesplat, load_cameras, load_ply,
                      read_ply_vertices, scene_camera_file)
from .label_spaces import SEGMENT_SPACES, to_nyu40


#: The warning of frames skipped for want of language features (filtered where they are not needed).
NO_LANGUAGE = "no language features"


class SceneDataError(SceneFormatError):
    """A scene folder is malformed; the message names the file (and frame) and the problem."""


@dataclass
class Frame:
    """One training view: its camera, the mask id map [H,W] int32 (-1 = no mask) at the chosen
    level, and the mask features [M,C] float32 (unit rows)."""

    name: str
    camera: Camera
    masks: np.ndarray
    features: np.ndarray


@dataclass
class ClassTable:
    """Open-vocabulary queries: ids [K] int64, names (K), text features [K,C] float32 unit rows."""

    ids: np.ndarray
    names: list[str]
    text_features: np.ndarray

    def subset(self, ids) -> "ClassTable":
        """The rows of the given class ids (those of the table only, in the order given)."""
        pos = {int(c): i for i, c in enumerate(self.ids)}
        rows = [pos[int(c)] for c in ids if int(c) in pos]
        return ClassTable(self.ids[rows], [self.names[r] for r in rows], self.text_features[rows])


@dataclass
class SceneData:
    """A loaded scene folder. ``gaussian_labels`` [N] (NYU40 ids), ``points`` [P,3] /
    ``point_labels`` [P] and ``instances`` [N] (-1 = none) are None when the folder has none."""

    root: Path
    gaussians: Gaussians
    frames: list[Frame]
    classes: ClassTable | None
    gaussian_labels: np.ndarray | None
    points: np.ndarray | None
    point_labels: np.ndarray | None
    instances: np.ndarray | None = None

    @property
    def name(self) -> str:
        return self.root.name

    @property
    def feature_dim(self) -> int:
        return self.frames[0].features.shape[1] if self.frames else 0


def unit_rows(a: np.ndarray) -> np.ndarray:
    """``a`` [..., C] scaled to unit rows along its last axis, float32 (zero rows stay zero)."""
    a = np.asarray(a, np.float32)
    return a / np.maximum(np.linalg.norm(a, axis=-1, keepdims=True), 1e-12)


def _load_npy(path: Path, frame: str) -> np.ndarray:
    if not path.is_file():
        raise SceneDataError(f"{path}: missing (language features of frame {frame!r})")
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise SceneDataError(f"{path}: not a readable .npy array ({exc})") from None


def _load_frame(folder: Path, cam: Camera, level: int) -> Frame:
    name = Path(cam.name).stem
    s_path, f_path = folder / f"{name}_s.npy", folder / f"{name}_f.npy"
    seg, feats = _load_npy(s_path, name), _load_npy(f_path, name)
    if seg.ndim == 2:
        seg = seg[None]
    if seg.ndim != 3:
        raise SceneDataError(f"{s_path}: frame {name!r}: mask map has shape {seg.shape}, expected [levels, H, W]")
    if not 0 <= level < seg.shape[0]:
        raise SceneDataError(f"{s_path}: frame {name!r}: level {level} requested, the file has {seg.shape[0]} levels")
    masks = seg[level]
    if not np.issubdtype(masks.dtype, np.integer):
        if not np.all(np.isfinite(masks)) or not np.all(masks == np.round(masks)):
            raise SceneDataError(f"{s_path}: frame {name!r}: mask ids must be integers, found non-integer values")
    masks = masks.astype(np.int32)
    h, w = masks.shape
    if (w, h) != (cam.width, cam.height):
        if abs(w / h - cam.width / cam.height) > 0.01 * cam.width / cam.height:
            raise SceneDataError(f"{s_path}: frame {name!r}: mask map is {w}x{h} (WxH) but cameras.json "
                                 f"says {cam.width}x{cam.height}, a different aspect ratio")
        cam = cam.resized(w, h)
    if feats.ndim != 2 or not np.issubdtype(feats.dtype, np.floating):
        raise SceneDataError(f"{f_path}: frame {name!r}: features have shape {feats.shape} ({feats.dtype}), "
                             "expected a float [masks, C] array")
    if not np.all(np.isfinite(feats)):
        raise SceneDataError(f"{f_path}: frame {name!r}: features contain NaN or infinite values")
    lo, hi = (int(masks.min()), int(masks.max())) if masks.size else (-1, -1)
    if lo < -1 or hi >= len(feats):
        raise SceneDataError(f"{s_path}: frame {name!r}: mask ids range over [{lo}, {hi}] but {f_path.name} "
                             f"has {len(feats)} rows (valid ids are -1..{len(feats) - 1})")
    start, end = level_rows(seg, level, len(feats))
    return Frame(name, cam, np.where(masks >= 0, masks - start, -1).astype(np.int32), unit_rows(feats[start:end]))


def level_rows(seg: np.ndarray, level: int, n_rows: int) -> tuple[int, int]:
    """The rows [start, end) of ``_f.npy`` that belong to mask level ``level`` of ``seg``
    [levels, H, W]. LangSplat stacks the features of its levels (default, s, m, l) and offsets
    level j's ids by the mask counts of the levels before it: level j's rows start at its
    smallest id and end where the next level's begin. Files whose levels share ids (no
    offsets) give every row to every level."""
    firsts = [int(m[m >= 0].min()) if (m >= 0).any() else None for m in seg]
    lasts = [int(m.max()) for m in seg]
    present = [j for j, f in enumerate(firsts) if f is not None]
    offset = all(lasts[a] < firsts[b] for a, b in zip(present, present[1:]))
    if not offset or firsts[level] is None:
        return 0, n_rows
    later = [firsts[j] for j in present if j > level]
    return firsts[level], later[0] if later else n_rows


def _load_classes(path: Path, dim: int | None) -> ClassTable:
    try:
        data = json.loads(path.read_text())
        entries = data["classes"]
        ids = np.array([int(e["id"]) for e in entries], np.int64)
        names = [str(e["name"]) for e in entries]
        feats = [np.asarray(e["text_feature"], np.float64) for e in entries]
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise SceneDataError(f"{path}: expected {{'classes': [{{'id', 'name', 'text_feature'}}]}} ({exc!r})") from None
    if len(set(ids.tolist())) != len(ids):
        raise SceneDataError(f"{path}: duplicate class ids")
    for i, f in enumerate(feats):
        if f.ndim != 1 or (dim is not None and len(f) != dim) or len(f) != len(feats[0]):
            want = dim if dim is not None else len(feats[0])
            raise SceneDataError(f"{path}: class {names[i]!r} has a text feature of shape {f.shape}; the "
                                 f"language features are {want}-D")
    return ClassTable(ids, names, unit_rows(np.stack(feats)) if feats else np.zeros((0, dim or 0), np.float32))


def read_labelled_points(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A labelled point cloud PLY (vertex x, y, z and an integer ``label``, e.g. ScanNet's
    ``*.labels.ply``): points [P,3] float64 and labels [P] int64."""
    columns, _ = read_ply_vertices(path)
    missing = [k for k in ("x", "y", "z", "label") if k not in columns]
    if missing:
        raise SceneDataError(f"{path}: labelled point cloud lacks vertex properties {missing}")
    points = np.stack([np.asarray(columns[k], np.float64) for k in "xyz"], 1)
    return points, np.asarray(columns["label"]).astype(np.int64)


def _scenesplat_labels(splat: SceneSplatFolder) -> np.ndarray | None:
    """A SceneSplat folder's labels as NYU40 ids [N] (-1 = ignored): the first of
    :data:`.label_spaces.SEGMENT_SPACES` it has, or None (a generic ``segment.npy`` names no space)."""
    name = next((n for n in SEGMENT_SPACES if splat.has(n)), None)
    if name is None:
        if splat.has("segment"):
            warnings.warn(f"{splat.root / 'segment.npy'}: labels of no known id space; not used as ground "
                          "truth (write labels/gaussian_labels.npy in NYU40 ids, docs/label-spaces.md)")
        return None
    try:
        return to_nyu40(splat.labels(name), SEGMENT_SPACES[name])
    except ValueError as exc:
        raise SceneDataError(f"{splat.root / (name + '.npy')}: {exc}") from None


def load_scene_folder(path, level: int = 0, require_language: bool = True) -> SceneData:
    """Load and validate a scene folder (module docstring). ``level`` picks the LangSplat mask level
    (0 = default). Frames without language-feature files raise (or are skipped with a warning when
    ``require_language`` is False)."""
    root = Path(path)
    if not root.is_dir():
        raise SceneDataError(f"{root}: not a scene folder")
    splat = SceneSplatFolder(root) if is_scenesplat(root) else None
    gaussians = splat.gaussians if splat else load_ply(root / "point_cloud.ply")
    camera_file = scene_camera_file(root, required=splat is None)
    cams = load_cameras(camera_file) if camera_file else []
    lang = root / "language_features"
    frames, skipped = [], []
    for cam in cams:
        stem = Path(cam.name).stem
        if not (lang / f"{stem}_s.npy").exists() and not require_language:
            skipped.append(stem)
            continue
        frames.append(_load_frame(lang, cam, level))
    if skipped:
        warnings.warn(f"{lang}: {NO_LANGUAGE} for {len(skipped)} of {len(cams)} frames "
                      f"(first: {skipped[0]!r}); skipped")
    dims = {f.features.shape[1] for f in frames if len(f.features)}
    if len(dims) > 1:
        per = {f.name: f.features.shape[1] for f in frames if len(f.features)}
        raise SceneDataError(f"{lang}: feature dims disagree between frames: {per}")
    dim = dims.pop() if dims else None
    classes = _load_classes(root / "classes.json", dim) if (root / "classes.json").is_file() else None
    labels = None
    label_path = root / "labels" / "gaussian_labels.npy"
    if label_path.is_file():
        labels = np.load(label_path).astype(np.int64)
        if labels.shape != (len(gaussians),):
            raise SceneDataError(f"{label_path}: {labels.shape} labels for {len(gaussians)} Gaussians in "
                                 f"{root / 'point_cloud.ply'}")
    elif splat is not None:
        labels = _scenesplat_labels(splat)
    points = point_labels = None
    if (root / "labels" / "points.ply").is_file():
        points, point_labels = read_labelled_points(root / "labels" / "points.ply")
    instances = splat.labels("instance") if splat is not None and splat.has("instance") else None
    return SceneData(root, gaussians, frames, classes, labels, points, point_labels, instances)
