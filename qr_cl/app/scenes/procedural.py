"""Procedural Gaussians made in code (no files needed): surfaces of flat Gaussians, a small scene
and a dense indoor room; used by `qr-cl bench`, the synthetic rooms, tests and examples."""
from __future__ import annotations

import numpy as np

from ...runtime import SH_C0
from ...scene import Camera, Gaussians, look_at


def surface_gaussians(points: np.ndarray, normals: np.ndarray, rgb: np.ndarray, size: float,
                      rng: np.random.Generator, jitter: tuple[float, float] = (0.7, 1.3),
                      colour_noise: float = 0.04, opacity: tuple[float, float] = (0.8, 0.99),
                      sh_degree: int = 1) -> Gaussians:
    """Flat Gaussians on a surface: points [n,3] and unit normals [n,3] (world units), the thin
    axis (z of the local frame, 0.1 ``size``) along the normal, in-plane sigmas ``size`` times a
    uniform factor in ``jitter``; colour ``rgb`` ([3] or [n,3] in [0,1]) plus Gaussian noise of
    ``colour_noise``, clipped; opacities uniform in ``opacity``; SH of ``sh_degree`` (0 or 1: a
    mild random view dependence)."""
    n = len(points)
    z = np.array([0.0, 0.0, 1.0])
    axis = np.cross(np.broadcast_to(z, normals.shape), normals)
    s = np.linalg.norm(axis, axis=1, keepdims=True)
    half = np.arctan2(s[:, 0], normals @ z) / 2
    axis = np.where(s > 1e-9, axis / np.maximum(s, 1e-12), np.array([1.0, 0.0, 0.0]))
    quats = np.concatenate([np.cos(half)[:, None], np.sin(half)[:, None] * axis], 1)
    scales = np.stack([size * rng.uniform(*jitter, n), size * rng.uniform(*jitter, n),
                       np.full(n, size * 0.1)], 1)
    colour = np.clip(np.broadcast_to(rgb, (n, 3)) + rng.normal(0, colour_noise, (n, 3)), 0, 1)
    sh = np.zeros((n, (sh_degree + 1) ** 2, 3))
    sh[:, 0] = (colour - 0.5) / SH_C0
    if sh_degree:
        sh[:, 1:] = rng.normal(0, 0.05, (n, 3, 3))
    return Gaussians(points.astype(np.float32), quats.astype(np.float32), scales.astype(np.float32),
                     rng.uniform(*opacity, n).astype(np.float32), sh.astype(np.float32))


def unit(v: np.ndarray) -> np.ndarray:
    """``v`` [..., D] divided by its norm along the last axis (unit vectors or rows)."""
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def concat(parts: list[Gaussians]) -> Gaussians:
    """One Gaussians of all ``parts`` (same SH degree), in order."""
    return Gaussians(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                       ("means", "quats", "scales", "opacities", "sh")))


def procedural_scene(n: int = 20000, seed: int = 0) -> Gaussians:
    """About ``n`` Gaussians (SH degree 1), z up, within [-1, 1]^2 x [0, 1.2]: a checkered floor,
    a red sphere, a blue torus and a yellow box. Deterministic for a given seed."""
    rng = np.random.default_rng(seed)
    parts = []
    k = n // 4
    # floor: a checkerboard on z = 0
    xy = rng.uniform(-1, 1, (k, 2))
    checker = ((np.floor(xy[:, 0] * 4) + np.floor(xy[:, 1] * 4)) % 2)[:, None]
    floor_rgb = 0.25 + 0.5 * checker * np.ones((1, 3))
    parts.append(surface_gaussians(np.c_[xy, np.zeros(k)], np.tile([0.0, 0.0, 1.0], (k, 1)),
                                    floor_rgb, 0.02, rng))
    # sphere
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    parts.append(surface_gaussians(np.array([-0.4, -0.3, 0.35]) + 0.3 * d, d,
                                    np.tile([0.85, 0.15, 0.1], (k, 1)), 0.02, rng))
    # torus (major radius 0.3, minor 0.1), standing on the floor
    u, v = rng.uniform(0, 2 * np.pi, (2, k))
    ring = np.c_[np.cos(u), np.sin(u), np.zeros(k)]
    normal = np.cos(v)[:, None] * ring + np.sin(v)[:, None] * np.array([0.0, 0.0, 1.0])
    parts.append(surface_gaussians(np.array([0.4, 0.3, 0.12]) + 0.3 * ring + 0.1 * normal, normal,
                                    np.tile([0.1, 0.3, 0.9], (k, 1)), 0.015, rng))
    # box: points on the six faces of a 0.4 x 0.4 x 0.5 box
    m = n - 3 * k
    face = rng.integers(0, 6, m)
    axis, sign = face // 2, np.where(face % 2, 1.0, -1.0)
    half = np.array([0.2, 0.2, 0.25])
    local = rng.uniform(-1, 1, (m, 3)) * half
    local[np.arange(m), axis] = sign * half[axis]
    normals = np.zeros((m, 3))
    normals[np.arange(m), axis] = sign
    parts.append(surface_gaussians(np.array([0.45, -0.45, 0.25]) + local, normals,
                                    np.tile([0.95, 0.8, 0.2], (m, 1)), 0.02, rng))
    return concat(parts)


def dense_room(n: int = 300_000, seed: int = 0, layers: int = 12,
               size: tuple[float, float, float] = (6.0, 5.0, 3.0), width: int = 640,
               height: int = 480) -> tuple[Gaussians, Camera]:
    """A dense indoor room like an optimized 3DGS capture (~``n`` Gaussians, SH degree 1), and a
    camera inside it: floor, ceiling and four walls each made of ``layers`` stacked layers of
    semi-transparent, anisotropic Gaussians (opacities 0.05..0.5, a 10 cm thick surface), plus
    1 % faint floaters in the air. Rays cross well over 100 Gaussians before V-Render saturates: the
    depth complexity at which the samplers separate. Lengths in metres, z up."""
    rng = np.random.default_rng(seed)
    w, d, h = size
    faces = [  # (origin, u axis, v axis, inward normal)
        ((0, 0, 0), (w, 0, 0), (0, d, 0), (0, 0, 1)), ((0, 0, h), (w, 0, 0), (0, d, 0), (0, 0, -1)),
        ((0, 0, 0), (w, 0, 0), (0, 0, h), (0, 1, 0)), ((0, d, 0), (w, 0, 0), (0, 0, h), (0, -1, 0)),
        ((0, 0, 0), (0, d, 0), (0, 0, h), (1, 0, 0)), ((w, 0, 0), (0, d, 0), (0, 0, h), (-1, 0, 0))]
    areas = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v, _ in faces])
    n_surface = int(0.99 * n)
    spacing = np.sqrt(layers * areas.sum() / n_surface)            # in-plane spacing per layer
    parts = []
    for (o, u, v, nrm), count in zip(faces, np.round(n_surface * areas / areas.sum()).astype(int)):
        uv = rng.random((count, 2))
        depth = rng.integers(0, layers, count) * (0.1 / layers)      # layers through 10 cm
        points = np.asarray(o) + uv[:, :1] * u + uv[:, 1:] * v + depth[:, None] * np.asarray(nrm)
        normals = np.tile(np.asarray(nrm, np.float64), (count, 1))
        colour = 0.35 + 0.4 * (np.floor(uv[:, :1] * 8) % 2) * np.array([0.6, 0.5, 0.3])
        parts.append(surface_gaussians(points, normals, colour, 1.5 * spacing, rng, jitter=(0.4, 2.5),
                                       colour_noise=0.08, opacity=(0.05, 0.5)))
    m = n - sum(len(p) for p in parts)                                # floaters
    floaters = surface_gaussians(rng.uniform((0.2, 0.2, 0.2), (w - 0.2, d - 0.2, h - 0.2), (m, 3)),
                                 unit(rng.normal(size=(m, 3))), rng.random((m, 3)), spacing, rng,
                                 jitter=(0.5, 1.5), colour_noise=0.0, opacity=(0.01, 0.05))
    f = 0.8125 * width                                               # 520 px at 640 px wide
    camera = look_at((0.25 * w, 0.2 * d, 0.45 * h), (0.8 * w, 0.9 * d, 0.35 * h), (0, 0, 1), f, f,
                     width, height, name="dense-room")
    return concat(parts + [floaters]), camera
