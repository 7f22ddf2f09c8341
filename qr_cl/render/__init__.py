"""The renderers above the stages: one engine per camera (:func:`render_view`: plan -> select ->
blend, differentiable in features, background, Gaussians and camera) under two adapters,
:func:`rasterize` (qr-cl's conventions) and :func:`rasterization` (gsplat's, with its
:func:`rasterize_top_contributing_gaussian_ids`); :func:`render_volume_fused`; the autograd
Functions and the selection cache; the render check and the runtime that passed it
(:func:`checked_runtime`), which the public calls render on.

Modules, each importing only those before it: autograd, cache, plan -> engine -> meta ->
selfcheck -> rasterize, gsplat_compat."""
from .autograd import BlendFunction, ProjectFunction, RasterFunction, SHColors, View, blend
from .cache import SelectionCache, selection_key
from .engine import Render, Splats2D, project_view, render_view
from .gsplat_compat import rasterization, rasterize_top_contributing_gaussian_ids
from .meta import RenderMeta
from .rasterize import rasterize, rasterize_plan, render_volume_fused
from .selfcheck import DeviceCheckError, check_in_child, checked_runtime, render_check

__all__ = ["BlendFunction", "DeviceCheckError", "ProjectFunction", "RasterFunction", "Render", "RenderMeta",
           "SHColors", "SelectionCache", "Splats2D", "View", "blend", "check_in_child", "checked_runtime",
           "project_view", "rasterization", "rasterize", "rasterize_plan",
           "rasterize_top_contributing_gaussian_ids", "render_check", "render_view", "render_volume_fused",
           "selection_key"]
