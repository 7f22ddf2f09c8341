"""Scenes: the Gaussian type, scene files (PLY, .splat, SceneSplat folders) and cameras."""
from .cameras import Camera, load_cameras, load_layout_instance, look_at, orbit_cameras, scene_camera_file
from .files import load_ply, load_scene, load_splat, ply_property_names, read_ply_vertices, save_ply
from .gaussians import Gaussians, SceneFormatError, quat_multiply, quat_to_rotmat, rgb_from_sh_dc
from .scenesplat import IGNORE_LABEL, SCENESPLAT_FILES, SceneSplatFolder, is_scenesplat, save_scenesplat

__all__ = ["IGNORE_LABEL", "SCENESPLAT_FILES", "Camera", "Gaussians", "SceneFormatError",
           "SceneSplatFolder", "is_scenesplat", "load_cameras", "load_layout_instance", "load_ply", "load_scene",
           "load_splat", "look_at", "orbit_cameras", "ply_property_names", "quat_multiply", "quat_to_rotmat",
           "read_ply_vertices", "rgb_from_sh_dc", "save_ply", "save_scenesplat", "scene_camera_file"]
