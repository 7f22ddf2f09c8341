"""Named scenes seen by one camera, as the benchmarks and the experiments time and measure them:
the real captures of a data folder, the procedural scene, the dense indoor room and stacks of
layers of known depth."""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...scene import Camera, Gaussians, load_ply, look_at, orbit_cameras
from .procedural import dense_room, procedural_scene

#: The real scenes of a data folder (as in the project's shared data): name -> file in the folder.
REAL_SCENES = {"fox": "wakufactory-fox/fox.ply", "donut": "v3dg-donut/donut_fused.ply"}


@dataclass
class SceneView:
    """A named scene with one camera."""

    name: str
    gaussians: Gaussians
    camera: Camera


def real_views(data: Path | None, width: int, height: int) -> list[SceneView]:
    """The real scenes of the folder ``data`` (:data:`REAL_SCENES`) with an orbit camera of
    ``width`` x ``height`` px; [] if ``data`` is None or holds none of them."""
    found = []
    for name, rel in REAL_SCENES.items():
        if data is not None and (data / rel).is_file():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                g = load_ply(data / rel)
            found.append(SceneView(name, g, orbit_cameras(g.means, 8, width, height)[1]))
    return found


def procedural_view(n: int, width: int, height: int) -> SceneView:
    """:func:`qr_cl.app.scenes.procedural.procedural_scene` with ``n`` Gaussians and an orbit camera."""
    g = procedural_scene(n)
    return SceneView(f"synthetic-{n // 1000}k", g, orbit_cameras(g.means, 8, width, height)[1])


def dense_view(n: int, width: int, height: int) -> SceneView:
    """:func:`qr_cl.app.scenes.procedural.dense_room` with ``n`` Gaussians and its camera."""
    g, cam = dense_room(n, width=width, height=height)
    return SceneView(f"dense-room-{n // 1000}k", g, cam)


def layered_view(depth: int, width: int, height: int) -> SceneView:
    """``depth`` screen-filling Gaussians stacked along the view axis, each with alpha 5/depth,
    so every ray meets exactly ``depth`` Gaussians (the complexity sweep's N)."""
    z = np.linspace(2.0, 3.0, depth)
    g = Gaussians(np.c_[np.zeros((depth, 2)), z].astype(np.float32),
                  np.tile([1.0, 0, 0, 0], (depth, 1)).astype(np.float32),
                  np.full((depth, 3), 50.0, np.float32),
                  np.full(depth, min(0.5, 5.0 / depth), np.float32), np.zeros((depth, 1, 3), np.float32))
    cam = look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], width, width, width, height)
    return SceneView(f"layers-{depth}", g, cam)


def room_overview_cameras(gaussians: Gaussians, width: int = 320, height: int = 240, n: int = 2,
                          fov_x_deg: float = 60.0) -> list[Camera]:
    """``n`` (<= 4) cameras that show a z-up room without a ceiling whole, nearly from above:
    over the box of the Gaussians' 2nd..98th percentile centres by 0.9 times its larger floor
    side, shifted from its centre by half its depth (and 15 % of its width) towards a side, each
    looks at the floor's centre 0.3 m up: the floor, the furniture and the inner faces of the
    walls are in view. Sides in the order -y, +y, -x, +x."""
    lo, hi = np.percentile(gaussians.means, 2, axis=0), np.percentile(gaussians.means, 98, axis=0)
    centre, size = (lo + hi) / 2, hi - lo
    fx = 0.5 * width / np.tan(np.radians(fov_x_deg) / 2)
    target = np.array([centre[0], centre[1], lo[2] + 0.3])
    shifts = ((-0.15, -0.5), (0.15, 0.5), (-0.5, 0.15), (0.5, -0.15))
    cams = []
    for i, (sx, sy) in enumerate(shifts[:n]):
        eye = np.array([centre[0] + sx * size[0], centre[1] + sy * size[1], hi[2] + 0.9 * max(size[0], size[1])])
        cams.append(look_at(eye, target, (0, 0, 1), fx, fx, width, height, f"overview_{i}"))
    return cams
