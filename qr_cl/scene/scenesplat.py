"""SceneSplat folders: one scene as Pointcept-style ``.npy`` files (SceneSplat-7K's format).

Layout (docs/scenesplat.md)::

    scene/
      coord.npy            [N,3] float centres, scene units
      color.npy            [N,3] uint8 0-255 (or float 0-1): the view-independent colour
      opacity.npy          [N] or [N,1] float, activated, in [0, 1]
      quat.npy             [N,4] float rotations, w,x,y,z (normalised here)
      scale.npy            [N,3] float standard deviations, linear (not log), >= 0
      sh.npy               optional [N,(d+1)^2,3] float SH coefficients (qr-cl's own file: when
                           present it gives the colour instead of color.npy, losslessly)
      normal.npy           optional [N,3]
      segment20.npy ...    optional [N] or [N,1] integer labels per Gaussian (-1 = ignored):
                           segment20 (ScanNet20 train ids), segment200 (ScanNet200), segment
      instance.npy         optional [N] or [N,1] integer instance ids (-1 = none)
      lang_feat.npy        optional [N,D] float language features, with valid_feat_mask.npy [N]

Every file is read once, when first asked for, and validated: its shape against the coordinates,
its dtype, non-finite values, ranges, and the quaternion order. A fault raises
:class:`SceneFormatError` naming the file and the problem, before any :class:`Gaussians` exist.
:func:`save_scenesplat` writes a folder (each file renamed into place once complete).
"""
from __future__ import annotations

import functools
import os
from pathlib import Path

import numpy as np

from ..runtime.constants import SH_C0
from .gaussians import Gaussians, SceneFormatError

#: The files every SceneSplat folder has.
SCENESPLAT_FILES = ("coord", "color", "opacity", "quat", "scale")
#: The ignore index of the label and instance files (Pointcept's and SceneSplat's ``ignore_index``):
#: a Gaussian without a class or an instance, in every label space.
IGNORE_LABEL = -1


def is_scenesplat(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a folder holding SceneSplat's ``coord.npy``."""
    return (Path(path) / "coord.npy").is_file()


class SceneSplatFolder:
    """A SceneSplat folder (module docstring) whose files are read on first use, once each."""

    def __init__(self, path: str | os.PathLike):
        self.root = Path(path)
        if not self.root.is_dir():
            raise SceneFormatError(f"{self.root}: no such SceneSplat folder")
        missing = [f"{name}.npy" for name in SCENESPLAT_FILES if not (self.root / f"{name}.npy").is_file()]
        if missing:
            raise SceneFormatError(f"{self.root}: not a SceneSplat folder, missing {', '.join(missing)}")
        self._arrays: dict[str, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self._read("coord", (3,)))

    def has(self, name: str) -> bool:
        """Whether the folder has ``<name>.npy``."""
        return (self.root / f"{name}.npy").is_file()

    def _load(self, name: str) -> np.ndarray:
        """``<name>.npy`` as stored, read on the first call only."""
        if name not in self._arrays:
            path = self.root / f"{name}.npy"
            if not path.is_file():
                raise SceneFormatError(f"{path}: no such file")
            try:
                self._arrays[name] = np.load(path, allow_pickle=False)
            except (ValueError, OSError, EOFError) as exc:
                raise SceneFormatError(f"{path}: not a readable .npy array ({exc})") from None
        return self._arrays[name]

    def _read(self, name: str, tail: tuple[int | None, ...], kind: str = "f") -> np.ndarray:
        """``<name>.npy`` checked to be [N, *tail] (None: any size; [N,1] is accepted for [N]) of
        dtype kind ``kind`` ("f" floating, "i" integer, "b" bool), and finite."""
        a, path = self._load(name), self.root / f"{name}.npy"
        if not tail and a.ndim == 2 and a.shape[1] == 1:
            a = a[:, 0]
        want = "[" + ", ".join(["N"] + ["D" if t is None else str(t) for t in tail]) + "]"
        if a.ndim != 1 + len(tail) or any(t is not None and s != t for s, t in zip(a.shape[1:], tail)):
            raise SceneFormatError(f"{path}: shape {list(a.shape)}, expected {want}")
        n = len(self._load("coord"))
        if len(a) != n:
            raise SceneFormatError(f"{path}: {len(a)} rows, but coord.npy has {n}")
        if a.dtype.kind not in {"f": "f", "i": "iu", "b": "biu"}[kind]:
            names = {"f": "a float", "i": "an integer", "b": "a bool"}[kind]
            raise SceneFormatError(f"{path}: dtype {a.dtype}, expected {names} array")
        if kind == "f" and not np.isfinite(a).all():
            rows = np.flatnonzero(~np.isfinite(a).reshape(n, -1).all(1))
            raise SceneFormatError(f"{path}: {len(rows)} rows hold NaN or infinite values (first: row {rows[0]})")
        return a

    def _colour(self) -> np.ndarray:
        """The SH coefficients [N,(d+1)^2,3] float32: sh.npy, else the DC term of color.npy."""
        if self.has("sh"):
            sh = self._read("sh", (None, 3))
            if sh.shape[1] not in (1, 4, 9, 16):
                raise SceneFormatError(f"{self.root / 'sh.npy'}: shape {list(sh.shape)}, expected [N, (d+1)^2, 3] "
                                       "with SH degree d <= 3")
            return sh.astype(np.float32)
        color, path = self._load("color"), self.root / "color.npy"
        if color.dtype.kind != "f" and color.dtype != np.uint8:
            raise SceneFormatError(f"{path}: dtype {color.dtype}; expected uint8 0-255 or float 0-1 colours")
        if color.dtype == np.uint8:
            rgb = self._read("color", (3,), "i").astype(np.float64) / 255.0
        else:
            rgb = self._read("color", (3,)).astype(np.float64)
            if rgb.size and (rgb.min() < 0 or rgb.max() > 1):
                raise SceneFormatError(f"{path}: {color.dtype} colours range over [{rgb.min():.4g}, {rgb.max():.4g}]; "
                                       "expected uint8 0-255 or float 0-1")
        return ((rgb - 0.5) / SH_C0).astype(np.float32)[:, None, :]

    @functools.cached_property
    def gaussians(self) -> Gaussians:
        """The activated Gaussians of the five files (and sh.npy when present); quaternions whose
        norm is off 1 by more than float32 rounding are normalised (:class:`Gaussians`)."""
        means = self._read("coord", (3,))
        sh = self._colour()
        opacity = self._read("opacity", ())
        if opacity.size and (opacity.min() < 0 or opacity.max() > 1):
            raise SceneFormatError(f"{self.root / 'opacity.npy'}: opacities range over [{opacity.min():.4g}, "
                                   f"{opacity.max():.4g}]; SceneSplat stores them activated, in [0, 1]")
        scales = self._read("scale", (3,))
        if scales.size and scales.min() < 0:
            raise SceneFormatError(f"{self.root / 'scale.npy'}: negative scales (min {scales.min():.4g}); SceneSplat "
                                   "stores linear standard deviations, not logs")
        quats = self._read("quat", (4,))
        _check_quat_order(self.root / "quat.npy", quats)
        norms = np.linalg.norm(quats.astype(np.float64), axis=1)
        if (norms == 0).any():
            raise SceneFormatError(f"{self.root / 'quat.npy'}: {int((norms == 0).sum())} zero quaternions "
                                   f"(first: row {int(np.flatnonzero(norms == 0)[0])})")
        return Gaussians(means.astype(np.float32, copy=False), quats.astype(np.float32, copy=False),
                         scales.astype(np.float32, copy=False), opacity.astype(np.float32, copy=False), sh)

    def labels(self, name: str) -> np.ndarray:
        """``<name>.npy``, a label file (segment20, segment200, segment) or instance, as [N] int64;
        ids below :data:`IGNORE_LABEL` raise."""
        a = self._load(name)
        if a.dtype.kind == "f":
            a = self._read(name, ())
            if (a != np.round(a)).any():
                raise SceneFormatError(f"{self.root / f'{name}.npy'}: labels must be integers, found fractions")
        else:
            a = self._read(name, (), "i")
        a = a.astype(np.int64)
        if a.size and a.min() < IGNORE_LABEL:
            raise SceneFormatError(f"{self.root / f'{name}.npy'}: label {a.min()} is below the ignore index {IGNORE_LABEL}")
        return a

    def language_features(self) -> tuple[np.ndarray, np.ndarray]:
        """``lang_feat`` [N,D] float32 and ``valid_feat_mask`` [N] bool (all True when absent)."""
        feats = self._read("lang_feat", (None,)).astype(np.float32, copy=False)
        valid = (self._read("valid_feat_mask", (), "b").astype(bool) if self.has("valid_feat_mask")
                 else np.ones(len(feats), bool))
        return feats, valid


def _check_quat_order(path: Path, quats: np.ndarray) -> None:
    """Refuse quaternions that are plainly x,y,z,w: a sign-canonical writer makes one component
    >= 0 in every row; if that is the last one while the first takes both signs, the real part
    is last. (Unit quaternions from 3DGS training have no such sign pattern and pass.)"""
    if len(quats) > 16 and (quats[:, 3] >= 0).all() and (quats[:, 0] < 0).any():
        raise SceneFormatError(f"{path}: the last component is >= 0 in every row and the first takes both signs: "
                               "x,y,z,w order? SceneSplat's quaternions are w,x,y,z")


def _save(path: Path, a: np.ndarray) -> None:
    tmp = path.with_name(path.name + ".tmp.npy")
    np.save(tmp, a)
    os.replace(tmp, path)


def save_scenesplat(folder: str | os.PathLike, gaussians: Gaussians, extra: dict[str, np.ndarray] | None = None) -> Path:
    """Write ``gaussians`` as a SceneSplat folder (module docstring): the five files, color.npy
    rounded to uint8, and sh.npy with the exact coefficients; ``extra`` maps more file names
    (``segment20``, ``instance``, ``lang_feat``, ...) to [N, ...] arrays. Each file is written to a
    temporary name and renamed."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    g = gaussians.to_numpy()
    rgb = np.clip(0.5 + SH_C0 * g.sh[:, 0].astype(np.float64), 0, 1)
    arrays = {"coord": g.means, "color": np.round(rgb * 255).astype(np.uint8), "opacity": g.opacities,
              "quat": g.quats, "scale": g.scales, "sh": g.sh, **(extra or {})}
    for name, a in arrays.items():
        if len(a) != len(g):
            raise ValueError(f"{name}: {len(a)} rows for {len(g)} Gaussians")
        _save(folder / f"{name}.npy", np.ascontiguousarray(a))
    return folder
