"""Gaussian scene files: INRIA 3DGS PLY and antimatter15 .splat I/O (activated :class:`Gaussians`);
:func:`load_scene` also opens folders (SceneSplat's, :mod:`.scenesplat`).

INRIA PLY stores raw values: ``opacity`` is a logit, ``scale_*`` are logs, ``rot_*`` an
unnormalised w,x,y,z quaternion, ``f_rest_*`` channel-major (R coefficients 1.., then G, then B).
:func:`load_ply` activates them; :func:`save_ply` writes them back.

Repairs of hostile values (each reported once per file with a warning, never silently):
- non-unit quaternions are normalised (zero quaternions become the identity);
- opacity logits of +/-inf are clamped to +/-``OPACITY_LOGIT_LIMIT`` (opacity 1 or 0);
- log-scales above ``LOG_SCALE_LIMIT`` are clamped (their exp would overflow float32);
- Gaussians with any NaN (or an infinite position, scale or colour) are dropped and counted.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from ..runtime.constants import SH_C0
from .gaussians import Gaussians, SceneFormatError
from .scenesplat import SceneSplatFolder, is_scenesplat

OPACITY_LOGIT_LIMIT = 30.0  # float32 sigmoid(30) == 1.0: a finite stand-in for +/-inf
LOG_SCALE_LIMIT = 80.0      # exp(80) ~ 5.5e34 is finite in float32 (exp(89) is not)

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return (1.0 / (1.0 + np.exp(-x.astype(np.float64)))).astype(np.float32)


def _logit(p: np.ndarray) -> np.ndarray:
    p = p.astype(np.float64)
    with np.errstate(divide="ignore"):
        raw = np.log(p) - np.log1p(-p)
    return np.clip(raw, -OPACITY_LOGIT_LIMIT, OPACITY_LOGIT_LIMIT).astype(np.float32)


# ----------------------------------------------------------------------------------------------
# PLY
# ----------------------------------------------------------------------------------------------

def _read_header(path: Path, fh) -> tuple[str, int, list[tuple[str, str]], int]:
    """Parse a PLY header: (format, vertex count, [(property, ply type)], header byte length)."""
    first = fh.readline()
    if first.strip() != b"ply":
        raise SceneFormatError(f"{path}: not a PLY file (first line is {first[:40]!r}, expected 'ply')")
    fmt, count, props, element = None, None, [], None
    while True:
        line = fh.readline()
        if not line:
            raise SceneFormatError(f"{path}: PLY header has no 'end_header' line")
        words = line.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            element = words[1]
            if element == "vertex":
                if count is not None:
                    raise SceneFormatError(f"{path}: PLY header declares 'vertex' twice")
                try:
                    count = int(words[2])
                except (IndexError, ValueError):
                    raise SceneFormatError(f"{path}: bad vertex count in header line {line!r}") from None
            elif count is None:
                raise SceneFormatError(f"{path}: element {element!r} comes before 'vertex'; "
                                       "3DGS PLY files have the vertex element first")
        elif words[0] == "property" and element == "vertex":
            if words[1] == "list":
                raise SceneFormatError(f"{path}: vertex property {words[-1]!r} is a list; 3DGS PLY "
                                       "vertex properties are scalars")
            if words[1] not in _PLY_TYPES:
                raise SceneFormatError(f"{path}: vertex property {words[2]!r} has unknown type {words[1]!r}")
            props.append((words[2], words[1]))
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise SceneFormatError(f"{path}: unsupported PLY format {fmt!r}")
    if count is None:
        raise SceneFormatError(f"{path}: PLY header has no 'element vertex' line")
    return fmt, count, props, fh.tell()


def read_ply_vertices(path: Path) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The vertex properties of a PLY file ({name: values}, {name: ply type}), with size checks."""
    with open(path, "rb") as fh:
        fmt, count, props, header_len = _read_header(path, fh)
        body = fh.read()
    names = [n for n, _ in props]
    if len(set(names)) != len(names):
        raise SceneFormatError(f"{path}: duplicate vertex property names in the header")
    if fmt == "ascii":
        rows = body.decode("ascii", "replace").split("\n")
        rows = [r for r in rows if r.strip()]
        if len(rows) < count:
            raise SceneFormatError(f"{path}: truncated: header declares {count} vertices but the body "
                                   f"has {len(rows)} lines")
        try:
            table = np.array([r.split() for r in rows[:count]], dtype=np.float64)
        except ValueError:
            bad = next(i for i, r in enumerate(rows[:count]) if len(r.split()) != len(props))
            raise SceneFormatError(f"{path}: vertex line {bad} has {len(rows[bad].split())} values, "
                                   f"the header declares {len(props)} properties") from None
        if table.ndim != 2 or table.shape[1] != len(props):
            raise SceneFormatError(f"{path}: vertex lines have {table.shape[-1]} values, the header "
                                   f"declares {len(props)} properties")
        return {n: table[:, i] for i, n in enumerate(names)}, dict(props)
    order = "<" if fmt == "binary_little_endian" else ">"
    dtype = np.dtype([(n, order + _PLY_TYPES[t]) for n, t in props])
    need = count * dtype.itemsize
    if len(body) < need:
        raise SceneFormatError(
            f"{path}: truncated: header declares {count} vertices of {dtype.itemsize} bytes "
            f"({need} bytes) but only {len(body)} bytes follow the header "
            f"({len(body) // max(dtype.itemsize, 1)} complete vertices)")
    table = np.frombuffer(body, dtype=dtype, count=count)
    return {n: table[n] for n in names}, dict(props)


def _sh_rest_count(path: Path, names: list[str]) -> int:
    rest = sorted(int(n[7:]) for n in names if n.startswith("f_rest_") and n[7:].isdigit())
    if rest != list(range(len(rest))):
        raise SceneFormatError(f"{path}: f_rest_* properties are not numbered 0..{len(rest) - 1}")
    if len(rest) not in (0, 9, 24, 45):
        raise SceneFormatError(f"{path}: {len(rest)} f_rest_* properties; SH degree 1, 2, 3 need "
                               "9, 24 or 45 (degree 0 has none)")
    return len(rest)


def load_ply(path: str | os.PathLike) -> Gaussians:
    """Read an INRIA 3DGS PLY (binary or ASCII; SH degree 0..3; with or without normals).

    Returns activated Gaussians (see :class:`Gaussians`). Raises SceneFormatError naming the file
    and the problem for malformed input; repairs hostile values with a warning (module docstring).
    """
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(f"{path}: no such file")
    columns, types = read_ply_vertices(path)
    n_rest = _sh_rest_count(path, list(columns))
    required = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
                "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    missing = [n for n in required if n not in columns]
    if missing:
        raise SceneFormatError(f"{path}: missing vertex properties {missing}; an INRIA 3DGS PLY needs "
                               f"{' '.join(required)} (and optionally f_rest_*, nx ny nz)")
    rest_names = [f"f_rest_{i}" for i in range(n_rest)]
    not_float = [f"{n} ({types[n]})" for n in required + rest_names if _PLY_TYPES[types[n]][0] != "f"]
    if not_float:
        raise SceneFormatError(f"{path}: properties must be float32 (or double), found {not_float}")

    def col(*names: str) -> np.ndarray:
        return np.stack([np.asarray(columns[n], np.float64) for n in names], axis=-1)

    means = col("x", "y", "z")
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :]
    coeffs = n_rest // 3
    rest = col(*rest_names).reshape(-1, 3, coeffs).transpose(0, 2, 1) if n_rest else dc[:, :0]
    sh = np.concatenate([dc, rest], axis=1)
    opacity_logit = np.asarray(columns["opacity"], np.float64)
    log_scales = col("scale_0", "scale_1", "scale_2")
    quats = col("rot_0", "rot_1", "rot_2", "rot_3")
    return _activate(path, means, sh, opacity_logit, log_scales, quats)


def _activate(path: Path, means, sh, opacity_logit, log_scales, quats) -> Gaussians:
    """Repair hostile raw values (with warnings) and convert raw storage to activated values."""
    bad = (np.isnan(opacity_logit) | ~np.isfinite(means).all(1) | ~np.isfinite(sh).all((1, 2))
           | ~np.isfinite(log_scales).all(1) | ~np.isfinite(quats).all(1))
    if bad.any():
        warnings.warn(f"{path}: dropped {int(bad.sum())} of {len(bad)} Gaussians with NaN or infinite "
                      "position, colour, scale or rotation")
        keep = ~bad
        means, sh, opacity_logit, log_scales, quats = (a[keep] for a in (means, sh, opacity_logit,
                                                                          log_scales, quats))
    inf = np.isinf(opacity_logit)
    if inf.any():
        warnings.warn(f"{path}: clamped {int(inf.sum())} infinite opacity logits to "
                      f"+/-{OPACITY_LOGIT_LIMIT:g} (opacity 1 or 0)")
    opacity_logit = np.clip(opacity_logit, -OPACITY_LOGIT_LIMIT, OPACITY_LOGIT_LIMIT)
    huge = log_scales > LOG_SCALE_LIMIT
    if huge.any():
        warnings.warn(f"{path}: clamped {int(huge.any(1).sum())} Gaussians' log-scales above "
                      f"{LOG_SCALE_LIMIT:g} (exp overflows float32)")
        log_scales = np.minimum(log_scales, LOG_SCALE_LIMIT)
    norms = np.linalg.norm(quats, axis=1, keepdims=True)
    zero = norms[:, 0] == 0
    if zero.any():
        warnings.warn(f"{path}: {int(zero.sum())} zero quaternions replaced by the identity rotation")
        quats[zero] = (1.0, 0.0, 0.0, 0.0)
        norms[zero] = 1.0
    off_unit = np.abs(norms[:, 0] - 1.0) > 1e-3
    if off_unit.any():
        warnings.warn(f"{path}: normalised {int(off_unit.sum())} non-unit quaternions (norms "
                      f"{norms.min():.3g}..{norms.max():.3g}); 3DGS stores them unnormalised")
    return Gaussians(means=means.astype(np.float32),
                     quats=(quats / norms).astype(np.float32),
                     scales=np.exp(log_scales).astype(np.float32),
                     opacities=_sigmoid(opacity_logit),
                     sh=sh.astype(np.float32))


def ply_property_names(sh_degree: int) -> list[str]:
    """INRIA property order for a given SH degree (no normals)."""
    n_rest = 3 * ((sh_degree + 1) ** 2 - 1)
    return (["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2"] + [f"f_rest_{i}" for i in range(n_rest)]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def save_ply(path: str | os.PathLike, gaussians: Gaussians, ascii: bool = False) -> None:
    """Write Gaussians as an INRIA 3DGS PLY (raw storage; binary little-endian unless ``ascii``).

    The file is written to a temporary name and renamed, so a failure never leaves half a file.
    """
    path = Path(path)
    g = gaussians
    rest = g.sh[:, 1:].transpose(0, 2, 1).reshape(len(g), -1)  # channel-major f_rest
    table = np.concatenate([
        g.means, g.sh[:, 0], rest, _logit(g.opacities)[:, None],
        np.log(np.maximum(g.scales, np.finfo(np.float32).tiny)), g.quats,
    ], axis=1).astype(np.float32)
    names = ply_property_names(g.sh_degree)
    header = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0",
              f"element vertex {len(g)}"] + [f"property float {n}" for n in names] + ["end_header"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        if ascii:
            np.savetxt(fh, table, fmt="%.9g")
        else:
            fh.write(table.astype("<f4").tobytes())
    os.replace(tmp, path)


# ----------------------------------------------------------------------------------------------
# antimatter15 .splat
# ----------------------------------------------------------------------------------------------

_SPLAT_DTYPE = np.dtype([("pos", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])


def load_splat(path: str | os.PathLike) -> Gaussians:
    """Read an antimatter15 ``.splat`` file (32-byte records: position, linear scale, RGBA u8,
    quaternion w,x,y,z as u8 = 128*q + 128) into activated Gaussians of SH degree 0."""
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(f"{path}: no such file")
    data = path.read_bytes()
    if len(data) % _SPLAT_DTYPE.itemsize:
        raise SceneFormatError(f"{path}: {len(data)} bytes is not a multiple of the 32-byte .splat "
                               "record (truncated file?)")
    rec = np.frombuffer(data, dtype=_SPLAT_DTYPE)
    rgba = rec["rgba"].astype(np.float64) / 255.0
    dc = ((rgba[:, :3] - 0.5) / SH_C0)[:, None, :]
    quats = (rec["rot"].astype(np.float64) - 128.0) / 128.0
    opacity = np.clip(rgba[:, 3], 1e-7, 1 - 1e-7)
    with np.errstate(divide="ignore", invalid="ignore"):
        log_scales = np.log(rec["scale"].astype(np.float64))
    return _activate(path, rec["pos"].astype(np.float64), dc, np.log(opacity) - np.log1p(-opacity),
                     log_scales, quats)


def load_scene(path: str | os.PathLike) -> Gaussians:
    """Load a ``.ply`` or ``.splat`` file by its suffix, or a folder: a SceneSplat folder
    (:mod:`.scenesplat`) or a scene folder's ``point_cloud.ply``."""
    path = Path(path)
    if path.is_dir():
        if (path / "point_cloud.ply").is_file() and not is_scenesplat(path):
            return load_ply(path / "point_cloud.ply")
        if not any(path.glob("*.npy")):
            raise SceneFormatError(f"{path}: a folder with neither point_cloud.ply nor SceneSplat's .npy files")
        return SceneSplatFolder(path).gaussians
    if path.suffix.lower() == ".splat":
        return load_splat(path)
    return load_ply(path)
