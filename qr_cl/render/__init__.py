"""The renderers above the stages: one engine per camera (:func:`render_view`: plan -> select ->
blend, differentiable in features, background and Gaussians) under two adapters, :func:`rasterize`
(qr-cl's conventions) and :func:`rasterization` (gsplat's); :func:`render_volume_fused`; the
autograd Functions and the selection cache."""
from .autograd import BlendFunction, RasterFunction, SHColours, View, blend
from .cache import SelectionCache, selection_key
from .engine import Render, render_view
from .gsplat_compat import rasterization
from .plan import rasterize_plan
from .rasterize import rasterize, render_volume_fused

__all__ = ["BlendFunction", "RasterFunction", "Render", "SHColours", "SelectionCache", "View", "blend",
           "rasterization", "rasterize", "rasterize_plan", "render_view", "render_volume_fused", "selection_key"]
