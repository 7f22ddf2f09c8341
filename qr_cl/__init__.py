"""qr-cl: Quantile Rendering and GS-Net on 3D Gaussian Splatting, with OpenCL kernels."""
from .camera import Camera, load_cameras, look_at, orbit_cameras
from .render import rasterize
from .scene import Gaussians, SceneFormatError, load_ply, load_scene, load_splat, save_ply

__all__ = ["Camera", "Gaussians", "SceneFormatError", "load_cameras", "load_ply", "load_scene",
           "load_splat", "look_at", "orbit_cameras", "rasterize", "save_ply"]
__version__ = "0.1.0"
