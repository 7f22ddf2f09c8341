"""Seeded synthetic labelled rooms written in the scene folder format (the embedded default data).

A room (floor, four walls) holds furniture-like objects of ScanNet classes built from open3d
primitives (boxes, cylinders, spheres) and wall-mounted doors, windows, pictures and curtains.
Cameras stand inside the room looking at objects; per-view instance masks are rendered with our
own renderer from the Gaussians' object ids. Two styles of Gaussians (``SyntheticConfig.style``):

- ``"flat"`` (the demo's default): flat Gaussians on the surfaces (thin axis along the normal,
  class colour plus noise, high opacity) and a few low-opacity floaters in the air. A ray meets
  an opaque surface and stops there, so every sampler picks nearly the same Gaussians.
- ``"3dgs"``: rooms that look like optimized 3DGS captures (:func:`splat_gaussians`): every
  surface is a semi-transparent shell ``thickness`` deep holding ``layers`` Gaussians per
  footprint, with log-normal anisotropic scales, random in-plane spins and tilts, Beta-distributed
  opacities (many faint, many nearly opaque, as real captures have) and ``floater_fraction`` of
  large faint floaters. Rays cross tens of Gaussians before V-Render saturates (the comparison
  with real scenes is in ``qr-cl reproduce``'s report). Ground truth: the generator's
  per-Gaussian labels (no labelled point cloud: Gaussians inside a shell are far from any
  surface point in their own Mahalanobis metric, so App. B would drop most of them).

"CLIP" features are SIMULATED: each class has a fixed random unit prototype (``dim``-D, seeded);
a mask's feature is normalize(prototype + ``mask_noise`` * random unit vector) and a class's text
feature is normalize(prototype + ``text_noise`` * another random unit vector) (the image/text
gap). Real CLIP features plug in through the same LangSplat files.

Folder written (see :mod:`qr_cl.data`): point_cloud.ply, cameras.json,
language_features/<frame>_s.npy [4,H,W] + <frame>_f.npy [M,dim], classes.json,
labels/gaussian_labels.npy [N] (class id, -1 for floaters), labels/points.ply (flat style only:
labelled point cloud with a ``label`` vertex property, for the App. B pseudo ground truth).
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..render import rasterize
from ..runtime import SH_C0
from ..scene import Camera, Gaussians, look_at, quat_multiply, save_ply
from .metrics import NYU40_NAMES
from .procedural import concat, surface_gaussians

GENERATOR_VERSION = 4
LEVELS = 4            # LangSplat's mask levels (default, s, m, l)
STYLES = ("flat", "3dgs")
#: SyntheticConfig fields read by the "3dgs" style only (left out of a flat room's cache key).
SPLAT_FIELDS = ("layers", "thickness", "opacity_beta", "floater_opacity_beta", "anisotropy")

#: class id -> base RGB colour in [0,1].
CLASS_COLOURS: dict[int, tuple[float, float, float]] = {
    1: (0.78, 0.76, 0.70), 2: (0.55, 0.42, 0.30), 3: (0.60, 0.35, 0.20), 4: (0.85, 0.85, 0.95),
    5: (0.70, 0.20, 0.15), 6: (0.25, 0.35, 0.60), 7: (0.45, 0.30, 0.15), 8: (0.90, 0.88, 0.80),
    9: (0.55, 0.75, 0.90), 10: (0.35, 0.22, 0.10), 11: (0.90, 0.60, 0.10), 12: (0.80, 0.80, 0.75),
    14: (0.50, 0.40, 0.30), 16: (0.65, 0.15, 0.35), 24: (0.95, 0.95, 0.95), 28: (0.40, 0.70, 0.70),
    33: (0.98, 0.98, 0.98), 34: (0.75, 0.75, 0.80), 35: (0.95, 0.90, 0.40), 36: (0.92, 0.92, 0.96),
}

FLOOR_CLASSES = (3, 4, 5, 6, 7, 10, 12, 14, 24, 33, 34, 36, 35)
WALL_CLASSES = (8, 9, 11, 16, 28)


@dataclass(frozen=True)
class SyntheticConfig:
    """Parameters of one synthetic room; lengths in metres, image sizes in pixels."""

    seed: int = 0
    n_gaussians: int = 24000
    n_objects: int = 7
    n_wall_objects: int = 3
    n_views: int = 12
    width: int = 160
    height: int = 120
    fov_deg: float = 75.0
    dim: int = 512
    mask_noise: float = 0.6
    text_noise: float = 0.3
    floater_fraction: float = 0.01
    points_per_gaussian: int = 16
    room_size: tuple[float, float, float] = (5.0, 4.0, 2.6)
    prototype_seed: int = 12345
    style: str = "flat"
    layers: float = 3.0                            # 3dgs: Gaussians stacked per footprint of a shell
    thickness: float = 0.03                        # 3dgs: shell depth behind each surface, m
    opacity_beta: tuple[float, float] = (0.6, 0.5)           # 3dgs: Beta(a, b) of surface opacities
    floater_opacity_beta: tuple[float, float] = (0.5, 6.0)   # 3dgs: Beta(a, b) of floater opacities
    anisotropy: float = 0.6                        # 3dgs: std of the log of each axis' scale factor

    def __post_init__(self) -> None:
        if self.style not in STYLES:
            raise ValueError(f"style={self.style!r}: choose one of {STYLES}")

    def params(self) -> dict:
        """The parameters the style reads (a flat room's leave out the "3dgs" style's fields, so
        its cache key and synthetic.json are those of the generator before the style existed)."""
        params = asdict(self)
        if self.style == "flat":
            for name in ("style",) + SPLAT_FIELDS:
                params.pop(name)
        return params

    def key(self) -> str:
        """A short hash of :meth:`params` and the generator version (the cache folder name)."""
        text = json.dumps({"v": GENERATOR_VERSION, **self.params()}, sort_keys=True)
        return hashlib.sha1(text.encode()).hexdigest()[:12]

    @property
    def folder_name(self) -> str:
        """The scene's folder name in the cache."""
        prefix = "room" if self.style == "flat" else "splat-room"
        return f"{prefix}-{self.seed}-{self.key()}"


def _open3d():
    """open3d, imported on first use (function-local: it takes ~0.9 s to import and only the room
    meshes need it)."""
    import open3d
    return open3d


def _box(size, centre, yaw: float = 0.0):
    o3d = _open3d()
    m = o3d.geometry.TriangleMesh.create_box(*size)
    m.translate(-np.asarray(size) / 2)
    m.rotate(_rot_z(yaw), center=(0, 0, 0))
    m.translate(centre)
    return m


def _cylinder(radius: float, height: float, centre):
    o3d = _open3d()
    m = o3d.geometry.TriangleMesh.create_cylinder(radius, height, resolution=24)
    m.translate(centre)
    return m


def _sphere(radius: float, centre):
    o3d = _open3d()
    m = o3d.geometry.TriangleMesh.create_sphere(radius, resolution=12)
    m.translate(centre)
    return m


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _furniture(cls: int, x: float, y: float, yaw: float) -> tuple[list, tuple[float, float]]:
    """Meshes of one floor-standing object of class ``cls`` at (x, y), and its footprint (sx, sy)."""
    r = _rot_z(yaw)

    def at(dx, dy, z):
        return np.array([x, y, 0.0]) + r @ np.array([dx, dy, z])

    def box(sx, sy, sz, dx=0.0, dy=0.0, z0=0.0):
        return _box((sx, sy, sz), at(dx, dy, z0 + sz / 2), yaw)

    if cls == 4:      # bed
        parts, fp = [box(2.0, 1.4, 0.45), box(0.4, 1.2, 0.15, -0.75, 0, 0.45)], (2.0, 1.4)
    elif cls == 5:    # chair
        legs = [_cylinder(0.025, 0.45, at(dx, dy, 0.225)) for dx in (-0.2, 0.2) for dy in (-0.2, 0.2)]
        parts, fp = legs + [box(0.48, 0.48, 0.06, z0=0.45), box(0.06, 0.48, 0.5, -0.21, 0, 0.51)], (0.5, 0.5)
    elif cls == 6:    # sofa
        parts = [box(1.8, 0.85, 0.42), box(1.8, 0.2, 0.45, 0, -0.33, 0.42),
                 box(0.2, 0.65, 0.25, -0.8, 0.1, 0.42), box(0.2, 0.65, 0.25, 0.8, 0.1, 0.42)]
        fp = (1.8, 0.85)
    elif cls == 7:    # table
        legs = [_cylinder(0.03, 0.72, at(dx, dy, 0.36)) for dx in (-0.65, 0.65) for dy in (-0.35, 0.35)]
        parts, fp = legs + [box(1.5, 0.85, 0.05, z0=0.72)], (1.5, 0.85)
    elif cls == 14:   # desk
        parts = [box(1.3, 0.65, 0.04, z0=0.72), box(0.05, 0.65, 0.72, -0.62, 0), box(0.45, 0.6, 0.72, 0.42, 0)]
        fp = (1.3, 0.65)
    elif cls == 33:   # toilet
        parts, fp = [_cylinder(0.2, 0.4, at(0.1, 0, 0.2)), box(0.2, 0.45, 0.4, -0.2, 0, 0.4)], (0.7, 0.45)
    elif cls == 35:   # lamp (unlisted class)
        parts, fp = [_cylinder(0.02, 1.4, at(0, 0, 0.7)), _sphere(0.18, at(0, 0, 1.5))], (0.4, 0.4)
    else:             # box-like: cabinet, bookshelf, counter, refrigerator, sink, bathtub
        size = {3: (0.8, 0.5, 0.9), 10: (0.9, 0.35, 1.8), 12: (1.5, 0.6, 0.9), 24: (0.7, 0.7, 1.8),
                34: (0.6, 0.45, 0.85), 36: (1.6, 0.75, 0.55)}[cls]
        parts, fp = [box(*size)], size[:2]
    return parts, fp


def _area_sample(meshes: list, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``n`` points [n,3] uniformly on the union of the meshes' surfaces, with unit normals [n,3]
    (numpy sampling, so the result depends on ``rng`` only)."""
    tris, normals = [], []
    for m in meshes:
        v, f = np.asarray(m.vertices), np.asarray(m.triangles)
        tris.append(v[f])
    tris = np.concatenate(tris)
    cross = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normals = cross / np.maximum(2 * area[:, None], 1e-12)
    pick = rng.choice(len(tris), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u, v = np.where(flip, 1 - u, u), np.where(flip, 1 - v, v)
    t = tris[pick]
    pts = t[:, 0] + u[:, None] * (t[:, 1] - t[:, 0]) + v[:, None] * (t[:, 2] - t[:, 0])
    return pts, normals[pick]


def _surface_area(meshes: list) -> float:
    return float(sum(m.get_surface_area() for m in meshes))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def class_prototypes(dim: int, seed: int) -> dict[int, np.ndarray]:
    """The simulated "CLIP" prototype of every class of :data:`NYU40_NAMES`: unit [dim] float64."""
    rng = np.random.default_rng(seed)
    return {c: _unit(rng.standard_normal(dim)) for c in sorted(NYU40_NAMES)}


def _layout(cfg: SyntheticConfig, rng: np.random.Generator) -> list[tuple[int, list]]:
    """Instances as (class id, meshes): floor, 4 walls, floor-standing and wall-mounted objects."""
    w, d, h = cfg.room_size
    t = 0.05
    inst = [(2, [_box((w, d, t), (w / 2, d / 2, -t / 2))])]
    walls = [((w, t, h), (w / 2, -t / 2, h / 2)), ((w, t, h), (w / 2, d + t / 2, h / 2)),
             ((t, d, h), (-t / 2, d / 2, h / 2)), ((t, d, h), (w + t / 2, d / 2, h / 2))]
    inst += [(1, [_box(size, c)]) for size, c in walls]
    placed: list[tuple[float, float, float, float]] = []
    classes = rng.choice(FLOOR_CLASSES, cfg.n_objects, replace=cfg.n_objects > len(FLOOR_CLASSES))
    for cls in classes:
        for _ in range(200):
            yaw = float(rng.integers(4)) * math.pi / 2
            _, (sx, sy) = _furniture(int(cls), 0, 0, yaw)
            ex, ey = (sx, sy) if abs(math.sin(yaw)) < 0.5 else (sy, sx)
            x, y = rng.uniform(ex / 2 + 0.1, w - ex / 2 - 0.1), rng.uniform(ey / 2 + 0.1, d - ey / 2 - 0.1)
            if all(abs(x - px) > (ex + pex) / 2 + 0.15 or abs(y - py) > (ey + pey) / 2 + 0.15
                   for px, py, pex, pey in placed):
                placed.append((x, y, ex, ey))
                inst.append((int(cls), _furniture(int(cls), x, y, yaw)[0]))
                break
    spans: dict[int, list[tuple[float, float]]] = {i: [] for i in range(4)}
    for cls in rng.choice(WALL_CLASSES, cfg.n_wall_objects, replace=cfg.n_wall_objects > len(WALL_CLASSES)):
        size = {8: (0.9, 2.0, 0.0), 9: (1.1, 1.0, 1.0), 11: (0.6, 0.45, 1.4), 16: (1.0, 2.1, 0.3),
                28: (0.9, 1.8, 0.2)}[int(cls)]
        for _ in range(100):
            wall = int(rng.integers(4))
            length = w if wall < 2 else d
            a = rng.uniform(size[0] / 2 + 0.2, length - size[0] / 2 - 0.2)
            if any(abs(a - b) < (size[0] + bw) / 2 + 0.1 for b, bw in spans[wall]):
                continue
            spans[wall].append((a, size[0]))
            zc, thick = size[2] + size[1] / 2, 0.03
            if wall < 2:
                y = thick / 2 + 0.01 if wall == 0 else d - thick / 2 - 0.01
                mesh = _box((size[0], thick, size[1]), (a, y, zc))
            else:
                x = thick / 2 + 0.01 if wall == 2 else w - thick / 2 - 0.01
                mesh = _box((thick, size[0], size[1]), (x, a, zc))
            inst.append((int(cls), [mesh]))
            break
    return inst


def _cameras(cfg: SyntheticConfig, targets: np.ndarray, footprints, rng: np.random.Generator) -> list[Camera]:
    """Cameras inside the room (outside object footprints) looking at object centres [T,3]."""
    w, d, _ = cfg.room_size
    fx = 0.5 * cfg.width / math.tan(math.radians(cfg.fov_deg) / 2)
    cams = []
    while len(cams) < cfg.n_views:
        eye = np.array([rng.uniform(0.3, w - 0.3), rng.uniform(0.3, d - 0.3), rng.uniform(1.3, 1.9)])
        if any(abs(eye[0] - x) < ex / 2 + 0.3 and abs(eye[1] - y) < ey / 2 + 0.3 for x, y, ex, ey in footprints):
            continue
        target = targets[rng.integers(len(targets))] + rng.normal(0, 0.2, 3)
        if np.linalg.norm((target - eye)[:2]) < 1.0:
            continue
        cams.append(look_at(eye, target, (0, 0, 1), fx, fx, cfg.width, cfg.height, f"frame_{len(cams):03d}"))
    return cams


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


def _camera_entry(i: int, cam: Camera) -> dict:
    r = cam.viewmat[:3, :3].astype(np.float64)
    return {"id": i, "img_name": cam.name, "width": cam.width, "height": cam.height,
            "position": cam.position.tolist(), "rotation": r.T.tolist(), "fx": cam.fx, "fy": cam.fy}


def _flat_gaussians(cfg: SyntheticConfig, instances: list, counts: np.ndarray, size: float,
                    rng: np.random.Generator) -> tuple[list[Gaussians], list[np.ndarray], np.ndarray, np.ndarray]:
    """The "flat" style: per instance ``counts[i]`` flat opaque Gaussians of in-plane sigma about
    ``size`` (m) on its surfaces, then the floaters up to ``cfg.n_gaussians``. Returns the parts,
    their instance ids (-1 = floater), and the labelled point cloud [P,3] with labels [P]."""
    parts, inst_ids, points, point_labels = [], [], [], []
    for i, ((cls, meshes), n) in enumerate(zip(instances, counts)):
        pts, nrm = _area_sample(meshes, int(n), rng)
        parts.append(surface_gaussians(pts, nrm, np.asarray(CLASS_COLOURS[cls]), size, rng, jitter=(0.8, 1.2),
                                       colour_noise=0.05, opacity=(0.85, 0.99), sh_degree=0))
        inst_ids.append(np.full(int(n), i))
        cloud, _ = _area_sample(meshes, int(n) * cfg.points_per_gaussian, rng)
        points.append(cloud)
        point_labels.append(np.full(len(cloud), cls))
    w, d, h = cfg.room_size
    n_float = max(cfg.n_gaussians - int(counts.sum()), 0)
    means = rng.uniform((0.2, 0.2, 0.2), (w - 0.2, d - 0.2, h - 0.2), (n_float, 3))
    quats = _unit(rng.standard_normal((n_float, 4)))
    opacities = rng.uniform(0.01, 0.2, n_float)
    sh = ((rng.random((n_float, 3)) - 0.5) / SH_C0)[:, None, :]
    parts.append(Gaussians(means.astype(np.float32), quats.astype(np.float32), np.full((n_float, 3), size, np.float32),
                           opacities.astype(np.float32), sh.astype(np.float32)))
    inst_ids.append(np.full(n_float, -1))
    return parts, inst_ids, np.concatenate(points), np.concatenate(point_labels)


def _axis_quats(axis: int, angles: np.ndarray) -> np.ndarray:
    """Unit w,x,y,z quaternions [n,4] of rotations by ``angles`` [n] (radians) about local ``axis``."""
    q = np.zeros((len(angles), 4))
    q[:, 0] = np.cos(angles / 2)
    q[:, 1 + axis] = np.sin(angles / 2)
    return q


def shell_gaussians(points: np.ndarray, normals: np.ndarray, rgb: np.ndarray, size: float, cfg: SyntheticConfig,
                    rng: np.random.Generator) -> Gaussians:
    """Gaussians of a semi-transparent surface shell, as 3DGS optimizes them: centres at
    ``points`` [n,3] moved up to ``cfg.thickness`` (m) inward along the unit ``normals`` [n,3];
    local frame with z along the normal, spun uniformly about it and tilted by a normal angle of
    0.3 rad; scales ``size`` (m) x (1, 0.6, 0.25) x log-normal factors of std ``cfg.anisotropy``;
    opacities Beta(``cfg.opacity_beta``); colour ``rgb`` [3] plus noise (SH degree 0)."""
    n = len(points)
    depth = rng.uniform(0.0, cfg.thickness, n)
    base = surface_gaussians(points - depth[:, None] * normals, normals, rgb, size, rng, colour_noise=0.06,
                             sh_degree=0)
    turn = quat_multiply(_axis_quats(2, rng.uniform(0, 2 * np.pi, n)), _axis_quats(0, rng.normal(0, 0.3, n)))
    quats = quat_multiply(base.quats.astype(np.float64), turn)
    scales = size * np.array([1.0, 0.6, 0.25]) * np.exp(rng.normal(0.0, cfg.anisotropy, (n, 3)))
    opacities = rng.beta(*cfg.opacity_beta, n)
    return Gaussians(base.means, _unit(quats).astype(np.float32), scales.astype(np.float32),
                     opacities.astype(np.float32), base.sh)


def splat_gaussians(cfg: SyntheticConfig, instances: list, counts: np.ndarray, size: float,
                    rng: np.random.Generator) -> tuple[list[Gaussians], list[np.ndarray]]:
    """The "3dgs" style: per instance ``counts[i]`` Gaussians in shells behind its surfaces
    (:func:`shell_gaussians` with sigma ``size``, m: the spacing of one of ``cfg.layers`` layers), then
    floaters up to ``cfg.n_gaussians``: anywhere in the room, random orientation, 0.1-0.5x the shell
    sigma, Beta(``cfg.floater_opacity_beta``) opacities, random colours. Returns the parts and
    their instance ids (-1 = floater)."""
    parts, inst_ids = [], []
    for i, ((cls, meshes), n) in enumerate(zip(instances, counts)):
        pts, nrm = _area_sample(meshes, int(n), rng)
        parts.append(shell_gaussians(pts, nrm, np.asarray(CLASS_COLOURS[cls]), size, cfg, rng))
        inst_ids.append(np.full(int(n), i))
    w, d, h = cfg.room_size
    m = max(cfg.n_gaussians - int(counts.sum()), 0)
    means = rng.uniform((0.1, 0.1, 0.1), (w - 0.1, d - 0.1, h - 0.1), (m, 3))
    scales = size * rng.uniform(0.1, 0.5, (m, 1)) * np.exp(rng.normal(0.0, cfg.anisotropy, (m, 3)))
    sh = ((rng.random((m, 3)) - 0.5) / SH_C0)[:, None, :]
    parts.append(Gaussians(means.astype(np.float32), _unit(rng.standard_normal((m, 4))).astype(np.float32),
                           scales.astype(np.float32), rng.beta(*cfg.floater_opacity_beta, m).astype(np.float32),
                           sh.astype(np.float32)))
    inst_ids.append(np.full(m, -1))
    return parts, inst_ids


def write_scene(out: Path, cfg: SyntheticConfig) -> None:
    """Generate the room of ``cfg`` into the (existing, empty) folder ``out``."""
    rng = np.random.default_rng(cfg.seed)
    instances = _layout(cfg, rng)
    areas = np.array([_surface_area(m) for _, m in instances])
    n_surface = int(round(cfg.n_gaussians * (1 - cfg.floater_fraction)))
    counts = np.maximum(np.round(n_surface * areas / areas.sum()).astype(int), 16)
    spacing = math.sqrt(areas.sum() / counts.sum())          # of the surface Gaussians, m
    points = None
    if cfg.style == "flat":
        parts, inst_ids, points, point_labels = _flat_gaussians(cfg, instances, counts, spacing, rng)
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
    cams = _cameras(cfg, targets, footprints, rng)
    (out / "cameras.json").write_text(json.dumps([_camera_entry(i, c) for i, c in enumerate(cams)], indent=1))

    protos = class_prototypes(cfg.dim, cfg.prototype_seed)
    feat_rng = np.random.default_rng(cfg.seed + 1)
    lang = out / "language_features"
    lang.mkdir()
    for cam, ids in zip(cams, _instance_maps(gaussians, instance, len(instances), cams)):
        present = [i for i in np.unique(ids) if i >= 0 and (ids == i).sum() >= 20]
        rows = np.full(len(instances) + 1, -1, np.int32)
        rows[present] = np.arange(len(present))
        seg = rows[ids]  # ids == -1 maps to rows[-1] == -1
        # LangSplat's layout: LEVELS mask levels, level j's ids offset by j * masks, and a
        # distinct simulated CLIP feature for each level's mask
        segs = np.stack([np.where(seg >= 0, seg + j * len(present), -1) for j in range(LEVELS)])
        feats = np.stack([_unit(protos[classes[i]] + cfg.mask_noise * _unit(feat_rng.standard_normal(cfg.dim)))
                          for _ in range(LEVELS) for i in present]) if present else np.zeros((0, cfg.dim))
        np.save(lang / f"{cam.name}_s.npy", segs.astype(np.int32))
        np.save(lang / f"{cam.name}_f.npy", feats.astype(np.float32))

    text_rng = np.random.default_rng(cfg.prototype_seed + 1)
    table = [{"id": c, "name": NYU40_NAMES[c],
              "text_feature": _unit(protos[c] + cfg.text_noise * _unit(text_rng.standard_normal(cfg.dim))).tolist()}
             for c in sorted(NYU40_NAMES)]
    (out / "classes.json").write_text(json.dumps({"feature_dim": cfg.dim, "classes": table}))
    (out / "labels").mkdir()
    np.save(out / "labels" / "gaussian_labels.npy", labels)
    if points is not None:
        write_labelled_points(out / "labels" / "points.ply", points, point_labels)
    (out / "synthetic.json").write_text(json.dumps({"generator_version": GENERATOR_VERSION, **cfg.params()}, indent=1))


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


def synthetic_scene(cfg: SyntheticConfig, cache: Path | None = None) -> Path:
    """The folder of the scene ``cfg`` under ``cache`` (default :func:`default_cache`), generated
    on first use (:func:`build_folder`)."""
    cache = Path(cache) if cache is not None else default_cache()
    return build_folder(cache / cfg.folder_name, "synthetic.json", lambda tmp: write_scene(tmp, cfg))
