"""The renderers above the stages: :func:`rasterize` (plan -> select -> blend, differentiable in
the features), :func:`render_volume_fused`, the autograd Function and the selection cache."""
from .autograd import BlendFunction, blend
from .cache import SelectionCache, selection_key
from .rasterize import rasterize, rasterize_plan, render_volume_fused

__all__ = ["BlendFunction", "SelectionCache", "blend", "rasterize", "rasterize_plan",
           "render_volume_fused", "selection_key"]
