"""qr-cl: Quantile Rendering and GS-Net on 3D Gaussian Splatting, with OpenCL kernels.

Layers, bottom to top: ``runtime`` (OpenCL device, launcher, memory, constants) -> ``scene``
(Gaussians, files, cameras) -> ``stages`` (one kernel each, beside its numpy twin) -> ``render``
(rasterize, autograd, cache) -> ``backbone`` (GS-Net's sparse UNet) -> ``app`` (data, training,
evaluation, demo, bench, CLI).
"""
from .render import (SelectionCache, rasterization, rasterize, rasterize_top_contributing_gaussian_ids,
                     render_volume_fused)
from .scene import (Camera, Gaussians, SceneFormatError, load_cameras, load_ply, load_scene,
                    load_splat, look_at, orbit_cameras, save_ply)

__all__ = ["Camera", "Gaussians", "SceneFormatError", "SelectionCache", "load_cameras", "load_ply",
           "load_scene", "load_splat", "look_at", "orbit_cameras", "rasterization", "rasterize",
           "rasterize_top_contributing_gaussian_ids", "render_volume_fused", "save_ply"]
__version__ = "0.1.0"
