"""Pinhole cameras: 3DGS ``cameras.json``, NeRF/Blender ``transform_matrix`` layouts, orbits.

A :class:`Camera` holds a world-to-camera 4x4 in the OpenCV convention used by 3DGS (x right,
y down, z forward) and intrinsics in pixels.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..runtime.constants import DEFAULTS
from .gaussians import SceneFormatError

# Blender/NeRF cameras look down -z with +y up; flipping y and z gives the OpenCV convention.
_OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class Camera:
    """viewmat [4,4] world-to-camera (OpenCV axes); fx, fy, cx, cy in pixels; width, height in px."""

    viewmat: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    name: str = ""

    @property
    def K(self) -> np.ndarray:
        """[3,3] intrinsic matrix."""
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1]], np.float32)

    @property
    def position(self) -> np.ndarray:
        """[3] camera centre in world coordinates."""
        r, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -r.T @ t

    def resized(self, width: int, height: int) -> "Camera":
        """The same camera at another resolution (intrinsics scaled per axis)."""
        sx, sy = width / self.width, height / self.height
        return Camera(self.viewmat, self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy,
                      int(width), int(height), self.name)


def _from_camera_to_world(c2w: np.ndarray) -> np.ndarray:
    """World-to-camera 4x4 from a camera-to-world 4x4 (rigid inverse)."""
    r, p = c2w[:3, :3], c2w[:3, 3]
    view = np.eye(4)
    view[:3, :3] = r.T
    view[:3, 3] = -r.T @ p
    return view.astype(np.float32)


def _field(path: Path, entry: dict, key: str, where: str):
    if key not in entry:
        raise SceneFormatError(f"{path}: {where} has no {key!r} field")
    return entry[key]


def _gs_camera(path: Path, i: int, entry: dict) -> Camera:
    """One entry of a 3DGS cameras.json (camera-to-world position and rotation columns)."""
    where = f"camera {i} ({entry.get('img_name', entry.get('id', '?'))})"
    width, height = int(_field(path, entry, "width", where)), int(_field(path, entry, "height", where))
    rot = np.asarray(_field(path, entry, "rotation", where), np.float64)
    pos = np.asarray(_field(path, entry, "position", where), np.float64)
    if rot.shape != (3, 3) or pos.shape != (3,):
        raise SceneFormatError(f"{path}: {where}: rotation must be 3x3 and position 3 numbers")
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = rot, pos
    return Camera(_from_camera_to_world(c2w), float(_field(path, entry, "fx", where)),
                  float(_field(path, entry, "fy", where)), width / 2, height / 2, width, height,
                  str(entry.get("img_name", i)))


def _nerf_camera(path: Path, name: str, c2w_gl, width: int, height: int, angle_x: float,
                 angle_y: float | None) -> Camera:
    """A Blender/NeRF camera (OpenGL camera-to-world, horizontal field of view in radians)."""
    fx = 0.5 * width / math.tan(0.5 * angle_x)
    fy = 0.5 * height / math.tan(0.5 * angle_y) if angle_y else fx
    return _opengl_camera(path, name, c2w_gl, fx, fy, width / 2, height / 2, width, height)


def _opengl_camera(path: Path, name: str, c2w_gl, fx: float, fy: float, cx: float, cy: float,
                   width: int, height: int) -> Camera:
    """A camera from an OpenGL camera-to-world 4x4 and pinhole intrinsics in pixels."""
    c2w = np.asarray(c2w_gl, np.float64)
    if c2w.shape != (4, 4):
        raise SceneFormatError(f"{path}: camera {name!r}: transform_matrix must be 4x4")
    if not np.isfinite(c2w).all():
        raise SceneFormatError(f"{path}: camera {name!r}: transform_matrix holds NaN or infinite values")
    return Camera(_from_camera_to_world(c2w @ _OPENGL_TO_OPENCV), fx, fy, cx, cy, width, height, name)


def _transforms_camera(path: Path, i: int, frame: dict, shared: dict) -> Camera:
    """One frame of NeRF/nerfstudio transforms: intrinsics ``fl_x``, ``fl_y``, ``cx``, ``cy``,
    ``w``, ``h`` (nerfstudio; per frame or shared) or ``camera_angle_x`` (Blender), the frame's
    values first."""
    name = str(frame.get("file_path", i))

    def get(key: str, default=None):
        value = frame.get(key, shared.get(key, default))
        if value is None:
            raise SceneFormatError(f"{path}: frame {name!r} has no {key!r} (nor has the file)")
        return value

    width, height = int(get("w")), int(get("h"))
    c2w = _field(path, frame, "transform_matrix", f"frame {name!r}")
    if "fl_x" not in frame and "fl_x" not in shared:
        return _nerf_camera(path, name, c2w, width, height, float(get("camera_angle_x")),
                            frame.get("camera_angle_y", shared.get("camera_angle_y")))
    fx = float(get("fl_x"))
    return _opengl_camera(path, name, c2w, fx, float(get("fl_y", fx)), float(get("cx", width / 2)),
                          float(get("cy", height / 2)), width, height)


def load_cameras(path: str | os.PathLike) -> list[Camera]:
    """Read cameras from a 3DGS ``cameras.json`` (a list of {width, height, position, rotation,
    fx, fy}), a V3DG layout (``layouts[].cameras[]`` with ``transform_matrix``), or a NeRF
    ``transforms.json`` (``frames[].transform_matrix``, with Blender's ``camera_angle_x`` or
    nerfstudio's ``fl_x``/``fl_y``/``cx``/``cy``, per frame or for all, and ``w``/``h``; camera
    names are the frames' ``file_path``).
    """
    path = Path(path)
    if not path.is_file():
        raise SceneFormatError(f"{path}: no such file")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise SceneFormatError(f"{path}: not valid JSON ({exc})") from None
    if isinstance(data, list):
        if not data:
            raise SceneFormatError(f"{path}: the camera list is empty")
        return [_gs_camera(path, i, e) for i, e in enumerate(data)]
    if isinstance(data, dict) and "layouts" in data:
        return [_nerf_camera(path, c.get("camera_name", str(i)), _field(path, c, "transform_matrix", "camera"),
                             int(c["camera_width"]), int(c["camera_height"]), float(c["camera_angle_x"]),
                             c.get("camera_angle_y"))
                for layout in data["layouts"] for i, c in enumerate(layout.get("cameras", []))]
    if isinstance(data, dict) and "frames" in data:
        if not data["frames"]:
            raise SceneFormatError(f"{path}: the frame list is empty")
        return [_transforms_camera(path, i, f, data) for i, f in enumerate(data["frames"])]
    raise SceneFormatError(f"{path}: not a 3DGS cameras.json (a list), a V3DG layout or NeRF transforms")


#: A scene folder's camera files, in the order looked for (3DGS, then SceneSplat's / NeRF's frames).
CAMERA_FILES = ("cameras.json", "transforms_train.json", "transforms.json")


def scene_camera_file(folder: str | os.PathLike, required: bool = True) -> Path | None:
    """The first of :data:`CAMERA_FILES` in ``folder``; when it has none, SceneFormatError naming
    the folder (``required``) or None."""
    folder = Path(folder)
    found = next((folder / name for name in CAMERA_FILES if (folder / name).is_file()), None)
    if found is None and required:
        raise SceneFormatError(f"{folder}: no cameras (looked for {', '.join(CAMERA_FILES)})")
    return found


def load_layout_instance(path: str | os.PathLike) -> tuple[float, np.ndarray, np.ndarray] | None:
    """(scale, quaternion w,x,y,z, translation) of the single asset instance of a V3DG layout file,
    or None when the file is not such a layout (or places more than one instance)."""
    try:
        data = json.loads(Path(path).read_text())
        instances = [i for layout in data["layouts"] for a in layout["assets"] for i in a["instances"]]
    except (json.JSONDecodeError, KeyError, TypeError):
        return None
    if len(instances) != 1:
        return None
    inst = instances[0]
    return (float(inst.get("scale", 1.0)), np.asarray(inst.get("quaternions", [1, 0, 0, 0]), np.float64),
            np.asarray(inst.get("positions", [0, 0, 0]), np.float64))


def look_at(eye, target, up, fx: float, fy: float, width: int, height: int, name: str = "") -> Camera:
    """A camera at ``eye`` looking at ``target`` with ``up`` pointing up in the image."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("look_at: view direction is parallel to up")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)  # image y points down
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = x, y, z, eye
    return Camera(_from_camera_to_world(c2w), fx, fy, width / 2, height / 2, width, height, name)


def orbit_cameras(means: np.ndarray, n: int, width: int = DEFAULTS.width, height: int = DEFAULTS.height,
                  fov_x_deg: float = 50.0, elevation_deg: float = 25.0, up_axis: int = 2,
                  distance_scale: float = 1.0) -> list[Camera]:
    """``n`` cameras on a circle around a point cloud ``means`` [N,3], all looking at its centre.

    The centre is the median of the points; the radius frames the 2nd..98th percentile box.
    ``up_axis`` is the world axis that points up (2 = z-up, 1 = y-up).
    """
    lo, hi = np.percentile(means, 2, axis=0), np.percentile(means, 98, axis=0)
    centre = np.median(means, axis=0)
    extent = 0.5 * np.linalg.norm(hi - lo)
    fx = 0.5 * width / math.tan(math.radians(fov_x_deg) / 2)
    fov_y = 2 * math.atan(0.5 * height / fx)
    dist = distance_scale * 1.1 * extent / math.sin(min(math.radians(fov_x_deg), fov_y) / 2)
    up = np.zeros(3)
    up[up_axis] = 1.0
    a, b = [ax for ax in range(3) if ax != up_axis]
    elev = math.radians(elevation_deg)
    cams = []
    for i in range(n):
        az = 2 * math.pi * i / n
        offset = np.zeros(3)
        offset[a] = math.cos(az) * math.cos(elev)
        offset[b] = math.sin(az) * math.cos(elev)
        offset[up_axis] = math.sin(elev)
        cams.append(look_at(centre + dist * offset, centre, up, fx, fx, width, height, f"orbit_{i:03d}"))
    return cams
