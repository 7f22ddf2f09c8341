"""The furniture of a synthetic room as open3d meshes (floor, walls, floor-standing and
wall-mounted objects of ScanNet classes, small objects on furniture tops), points sampled on them,
and cameras inside the room.

Classes are drawn with weights that follow ScanNet's instance frequencies roughly (chairs the most
common object, then tables, cabinets, doors; bathtubs and shower curtains rare); walls and floor
dominate by area."""
from __future__ import annotations

import math

import numpy as np

from ...scene import Camera, look_at
from .room_config import SyntheticConfig

#: floor-standing class id -> relative weight of drawing it.
FLOOR_CLASSES = {5: 8.0, 7: 3.0, 3: 3.0, 14: 2.0, 6: 1.5, 4: 1.0, 10: 1.0, 35: 1.0, 12: 0.7, 24: 0.5, 33: 0.5,
                 34: 0.5, 36: 0.3}

#: wall-mounted class id -> relative weight.
WALL_CLASSES = {8: 3.0, 9: 2.0, 11: 2.0, 16: 1.0, 28: 0.3}

#: small object class id -> (box size (x, y, z) in m, the floor classes it may stand on).
SMALL_OBJECTS = {18: ((0.5, 0.35, 0.12), (4, 6)), 23: ((0.25, 0.18, 0.2), (7, 14, 10, 3, 12)),
                 29: ((0.35, 0.3, 0.25), (7, 14, 3, 12)), 25: ((0.8, 0.08, 0.5), (14, 3, 12)),
                 35: ((0.24, 0.24, 0.45), (7, 14, 3))}

#: floor class id -> height of its top surface, m (what a small object stands on).
TOP_HEIGHT = {3: 0.9, 4: 0.45, 6: 0.42, 7: 0.77, 10: 1.8, 12: 0.9, 14: 0.76}


def _draw(weights: dict[int, float], n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` class ids drawn from ``weights`` (with replacement)."""
    ids = np.array(list(weights))
    p = np.array(list(weights.values()))
    return rng.choice(ids, n, p=p / p.sum())


def _open3d():
    """open3d, imported on first use (function-local: it is slow to import and only the room
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


def area_sample(meshes: list, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
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


def surface_area(meshes: list) -> float:
    return float(sum(m.get_surface_area() for m in meshes))


def room_instances(cfg: SyntheticConfig, rng: np.random.Generator) -> list[tuple[int, list]]:
    """Instances as (class id, meshes): floor, 4 walls, floor-standing and wall-mounted objects."""
    w, d, h = cfg.room_size
    t = 0.05
    inst = [(2, [_box((w, d, t), (w / 2, d / 2, -t / 2))])]
    walls = [((w, t, h), (w / 2, -t / 2, h / 2)), ((w, t, h), (w / 2, d + t / 2, h / 2)),
             ((t, d, h), (-t / 2, d / 2, h / 2)), ((t, d, h), (w + t / 2, d / 2, h / 2))]
    inst += [(1, [_box(size, c)]) for size, c in walls]
    placed: list[tuple[float, float, float, float]] = []
    hosts: list[tuple[int, float, float, float, float, float]] = []     # class, x, y, ex, ey, yaw
    for cls in _draw(FLOOR_CLASSES, cfg.n_objects, rng):
        for _ in range(200):
            yaw = float(rng.integers(4)) * math.pi / 2
            _, (sx, sy) = _furniture(int(cls), 0, 0, yaw)
            ex, ey = (sx, sy) if abs(math.sin(yaw)) < 0.5 else (sy, sx)
            x, y = rng.uniform(ex / 2 + 0.1, w - ex / 2 - 0.1), rng.uniform(ey / 2 + 0.1, d - ey / 2 - 0.1)
            if all(abs(x - px) > (ex + pex) / 2 + 0.15 or abs(y - py) > (ey + pey) / 2 + 0.15
                   for px, py, pex, pey in placed):
                placed.append((x, y, ex, ey))
                hosts.append((int(cls), x, y, ex, ey, yaw))
                inst.append((int(cls), _furniture(int(cls), x, y, yaw)[0]))
                break
    spans: dict[int, list[tuple[float, float]]] = {i: [] for i in range(4)}
    for cls in _draw(WALL_CLASSES, cfg.n_wall_objects, rng):
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
    return inst + _small_objects(cfg, hosts, rng)


def _small_objects(cfg: SyntheticConfig, hosts: list, rng: np.random.Generator) -> list[tuple[int, list]]:
    """Up to ``cfg.n_small_objects`` small objects (:data:`SMALL_OBJECTS`), each on the top of a
    placed floor object it may stand on, at a random spot of that top; none where no host fits."""
    out = []
    for cls in _draw({c: 1.0 for c in SMALL_OBJECTS}, cfg.n_small_objects, rng):
        size, on = SMALL_OBJECTS[int(cls)]
        fitting = [h for h in hosts if h[0] in on]
        if not fitting:
            continue
        host, x, y, ex, ey, yaw = fitting[rng.integers(len(fitting))]
        top = TOP_HEIGHT[host]
        dx = rng.uniform(-max(ex - size[0], 0) / 2, max(ex - size[0], 0) / 2)
        dy = rng.uniform(-max(ey - size[1], 0) / 2, max(ey - size[1], 0) / 2)
        centre = (x + dx, y + dy, top + size[2] / 2 + 0.005)
        if int(cls) == 35:      # table lamp: a stem and a shade
            meshes = [_cylinder(0.02, size[2] * 0.6, (centre[0], centre[1], top + size[2] * 0.3)),
                      _sphere(size[0] / 2, (centre[0], centre[1], top + size[2] - size[0] / 2))]
        else:
            meshes = [_box(size, centre, yaw + float(rng.normal(0, 0.2)))]
        out.append((int(cls), meshes))
    return out


def room_cameras(cfg: SyntheticConfig, targets: np.ndarray, footprints, rng: np.random.Generator) -> list[Camera]:
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
