"""The renderers above the stages: one engine per camera (:func:`render_view`: plan -> select ->
blend, differentiable in features, background, Gaussians and camera) under two adapters,
:func:`rasterize` (qr-cl's conventions) and :func:`rasterization` (gsplat's, with its
:func:`rasterize_top_contributing_gaussian_ids`); :func:`render_volume_fused`; the autograd
Functions and the selection cache."""
from .autograd import BlendFunction, ProjectFunction, RasterFunction, SHColours, View, blend
from .cache import SelectionCache, selection_key
from .engine import Render, Splats2D, project_view, render_view
from .gsplat_compat import rasterization, rasterize_top_contributing_gaussian_ids
from .plan import rasterize_plan
from .rasterize import rasterize, render_volume_fused

__all__ = ["BlendFunction", "ProjectFunction", "RasterFunction", "Render", "SHColours", "SelectionCache", "Splats2D",
           "View", "blend", "project_view", "rasterization", "rasterize", "rasterize_plan",
           "rasterize_top_contributing_gaussian_ids", "render_view", "render_volume_fused", "selection_key"]
