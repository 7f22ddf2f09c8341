"""The viewer's cameras: an overview that frames the whole scene (the page's first view), then the
scene's own cameras, which the page steps through.

The overview of a scene folder whose cameras stand z-up (a room) is the first overview camera of
the pictures of ``qr-cl demo`` and ``qr-cl eval`` (:func:`~qr_cl.app.scenes.views.room_overview_cameras`);
any other scene gets an orbit view that frames its Gaussians, up as its cameras (or ``up_axis``
for a bare file without cameras), from the side of its first camera.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from ...scene import Camera, Gaussians, orbit_cameras
from ..scenes.views import room_overview_cameras

#: Cameras whose mean up vector is this close (cosine) to +z make a z-up room.
Z_UP_COSINE = 0.8


def _unit(v: np.ndarray) -> np.ndarray:
    return v / max(float(np.linalg.norm(v)), 1e-12)


def scene_radius(means: np.ndarray) -> float:
    """Half the diagonal of the 2nd..98th percentile box of ``means`` [N,3] (world units)."""
    lo, hi = np.percentile(means, 2, axis=0), np.percentile(means, 98, axis=0)
    return float(0.5 * np.linalg.norm(hi - lo))


def camera_view(cam: Camera, up: np.ndarray, centre: np.ndarray, radius: float, name: str) -> dict:
    """The page's view of a pinhole camera ``cam``: {"name", "eye", "target", "up", "fov_y"}, the
    target on its optical axis as deep as ``centre`` (at least a tenth of ``radius``) so that
    orbiting turns about the scene; ``up`` [3] is the world's up."""
    eye, forward = cam.position, cam.viewmat[2, :3]
    depth = max(float((centre - eye) @ forward), 0.1 * radius)
    return {"name": name, "eye": eye.tolist(), "target": (eye + depth * forward).tolist(),
            "up": _unit(np.asarray(up, np.float64)).tolist(),
            "fov_y": math.degrees(2 * math.atan(0.5 * cam.height / cam.fy))}


def orbit_view(means: np.ndarray, up: np.ndarray, towards: np.ndarray, width: int, height: int) -> dict:
    """The overview of :func:`~qr_cl.scene.orbit_cameras` (framing the 2nd..98th percentile box
    of ``means`` [N,3] from above their median) about the world's ``up`` [3], on the side of
    ``towards`` [3] (a world point, e.g. a camera's position), as a view of :func:`camera_view`."""
    up = _unit(np.asarray(up, np.float64))
    centre = np.median(means, axis=0)
    side = np.asarray(towards, np.float64) - centre
    side = side - (side @ up) * up
    if np.linalg.norm(side) < 1e-9:                                    # any direction normal to up
        side = np.cross(up, np.eye(3)[int(np.argmin(np.abs(up)))])
    side = _unit(side)
    turn = np.stack([side, np.cross(up, side), up])      # world -> a frame with up as +z, side as +x
    cam = orbit_cameras(means @ turn.T, 1, width, height)[0]
    world = np.eye(4)
    world[:3, :3] = turn
    return camera_view(replace(cam, viewmat=cam.viewmat @ world), up, centre, scene_radius(means), "overview")


def scene_views(gaussians: Gaussians, cameras: list[Camera], width: int, height: int, up_axis: int = 2
                ) -> list[dict]:
    """The page's views of ``gaussians`` with their ``cameras``: the overview (module docstring),
    then one view per camera (:func:`camera_view`, named after its image). ``width`` x ``height``
    px is the page's frame size; ``up_axis`` the world's up axis (2 = z, 1 = y) without cameras."""
    means = gaussians.means
    radius, centre = scene_radius(means), np.median(means, axis=0)
    if not cameras:
        up = np.eye(3)[up_axis]
        return [orbit_view(means, up, centre + np.roll(up, 1), width, height)]
    up = _unit(np.stack([-c.viewmat[1, :3] for c in cameras]).mean(0))
    if up[2] >= Z_UP_COSINE:
        room = room_overview_cameras(gaussians, width, height, n=1)[0]
        overview = camera_view(room, np.eye(3)[2], centre, radius, "overview")
    else:
        overview = orbit_view(means, up, cameras[0].position, width, height)
    return [overview, *(camera_view(c, up, centre, radius, c.name or f"camera {i}") for i, c in enumerate(cameras))]
