"""The renderers above the stages: the rays of one camera, selected and blended (:mod:`.rays`:
the API every path renders through, the engine's and the app's), one engine per camera
(:func:`render_view`: plan -> select and blend, differentiable in features, background, Gaussians
and camera) under two adapters, :func:`rasterize` (qr-cl's conventions) and :func:`rasterization`
(gsplat's, with its :func:`rasterize_top_contributing_gaussian_ids`); :func:`render_volume_fused`;
the autograd Functions and the selection cache; the render check and the runtime that passed it
(:func:`checked_runtime`), which the public calls render on.

Modules, each importing only those before it: rays -> autograd, cache, plan -> engine -> meta ->
selfcheck -> rasterize, gsplat_compat."""
from .autograd import BlendFunction, ProjectFunction, RasterFunction, SHColors, View, blend
from .cache import SelectionCache, selection_key
from .engine import Render, Splats2D, project_view, render_view
from .gsplat_compat import rasterization, rasterize_top_contributing_gaussian_ids
from .meta import RenderMeta
from .rasterize import rasterize, rasterize_plan, render_volume_fused
from .rays import (BackwardIndex, RasterPlan, Selection, blend_rays, compact_selections, concat_selections, gather_rays,
                   listed_selection, prepare_backward, ray_entries, select_and_blend_rays, select_rays, weighted_sums)
from .selfcheck import DeviceCheckError, check_in_child, checked_runtime, render_check

__all__ = ["BackwardIndex", "BlendFunction", "DeviceCheckError", "ProjectFunction", "RasterFunction", "RasterPlan",
           "Render", "RenderMeta", "SHColors", "Selection", "SelectionCache", "Splats2D", "View", "blend",
           "blend_rays", "check_in_child", "checked_runtime", "compact_selections", "concat_selections",
           "gather_rays", "listed_selection", "prepare_backward", "project_view", "rasterization", "rasterize",
           "rasterize_plan", "rasterize_top_contributing_gaussian_ids", "ray_entries", "render_check",
           "render_view", "render_volume_fused", "select_and_blend_rays", "select_rays", "selection_key",
           "weighted_sums"]
