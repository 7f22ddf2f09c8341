"""The Gaussians of a synthetic room's surfaces, in its two styles: flat opaque Gaussians, or the
semi-transparent shells of an optimized 3DGS capture (see :mod:`qr_cl.app.scenes.synthetic`)."""
from __future__ import annotations

import numpy as np

from ...runtime import SH_C0
from ...scene import Gaussians, quat_multiply
from .procedural import surface_gaussians, unit
from .room_config import SyntheticConfig
from .room_layout import area_sample

#: class id -> base RGB colour in [0,1].
CLASS_COLOURS: dict[int, tuple[float, float, float]] = {
    1: (0.78, 0.76, 0.70), 2: (0.55, 0.42, 0.30), 3: (0.60, 0.35, 0.20), 4: (0.85, 0.85, 0.95),
    5: (0.70, 0.20, 0.15), 6: (0.25, 0.35, 0.60), 7: (0.45, 0.30, 0.15), 8: (0.90, 0.88, 0.80),
    9: (0.55, 0.75, 0.90), 10: (0.35, 0.22, 0.10), 11: (0.90, 0.60, 0.10), 12: (0.80, 0.80, 0.75),
    14: (0.50, 0.40, 0.30), 16: (0.65, 0.15, 0.35), 18: (0.85, 0.55, 0.55), 23: (0.20, 0.45, 0.25),
    24: (0.95, 0.95, 0.95), 25: (0.10, 0.10, 0.12), 28: (0.40, 0.70, 0.70), 29: (0.70, 0.55, 0.35),
    33: (0.98, 0.98, 0.98), 34: (0.75, 0.75, 0.80), 35: (0.95, 0.90, 0.40), 36: (0.92, 0.92, 0.96),
}


def flat_gaussians(cfg: SyntheticConfig, instances: list, counts: np.ndarray, size: float,
                   rng: np.random.Generator) -> tuple[list[Gaussians], list[np.ndarray], np.ndarray, np.ndarray]:
    """The "flat" style: per instance ``counts[i]`` flat opaque Gaussians of in-plane sigma about
    ``size`` (m) on its surfaces, then the floaters up to ``cfg.n_gaussians``. Returns the parts,
    their instance ids (-1 = floater), and the labelled point cloud [P,3] with labels [P]."""
    parts, inst_ids, points, point_labels = [], [], [], []
    for i, ((cls, meshes), n) in enumerate(zip(instances, counts)):
        pts, nrm = area_sample(meshes, int(n), rng)
        parts.append(surface_gaussians(pts, nrm, np.asarray(CLASS_COLOURS[cls]), size, rng, jitter=(0.8, 1.2),
                                       colour_noise=0.05, opacity=(0.85, 0.99), sh_degree=0))
        inst_ids.append(np.full(int(n), i))
        cloud, _ = area_sample(meshes, int(n) * cfg.points_per_gaussian, rng)
        points.append(cloud)
        point_labels.append(np.full(len(cloud), cls))
    w, d, h = cfg.room_size
    n_float = max(cfg.n_gaussians - int(counts.sum()), 0)
    means = rng.uniform((0.2, 0.2, 0.2), (w - 0.2, d - 0.2, h - 0.2), (n_float, 3))
    quats = unit(rng.standard_normal((n_float, 4)))
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
    return Gaussians(base.means, unit(quats).astype(np.float32), scales.astype(np.float32),
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
        pts, nrm = area_sample(meshes, int(n), rng)
        parts.append(shell_gaussians(pts, nrm, np.asarray(CLASS_COLOURS[cls]), size, cfg, rng))
        inst_ids.append(np.full(int(n), i))
    w, d, h = cfg.room_size
    m = max(cfg.n_gaussians - int(counts.sum()), 0)
    means = rng.uniform((0.1, 0.1, 0.1), (w - 0.1, d - 0.1, h - 0.1), (m, 3))
    scales = size * rng.uniform(0.1, 0.5, (m, 1)) * np.exp(rng.normal(0.0, cfg.anisotropy, (m, 3)))
    sh = ((rng.random((m, 3)) - 0.5) / SH_C0)[:, None, :]
    parts.append(Gaussians(means.astype(np.float32), unit(rng.standard_normal((m, 4))).astype(np.float32),
                           scales.astype(np.float32), rng.beta(*cfg.floater_opacity_beta, m).astype(np.float32),
                           sh.astype(np.float32)))
    inst_ids.append(np.full(m, -1))
    return parts, inst_ids
