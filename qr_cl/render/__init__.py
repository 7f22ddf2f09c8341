"""The renderers above the stages: :func:`rasterize` (plan -> select -> blend, differentiable in
the features), :func:`rasterization` (gsplat's interface, differentiable in the Gaussians too),
:func:`render_volume_fused`, the autograd Functions and the selection cache."""
from .autograd import BlendFunction, RasterFunction, View, blend, view_selection
from .cache import SelectionCache, selection_key
from .gsplat_compat import rasterization
from .plan import rasterize_plan
from .rasterize import rasterize, render_volume_fused

__all__ = ["BlendFunction", "RasterFunction", "SelectionCache", "View", "blend", "rasterization", "rasterize",
           "rasterize_plan", "render_volume_fused", "selection_key", "view_selection"]
