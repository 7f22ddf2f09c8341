"""The pipeline stages, one module per kernel file, each but transpose beside its float64 twin
(``*_ref``): project -> binning (RasterPlan) -> sh (colour) -> select (Selection) -> blend (and
backward: a scatter, or a gather over the selection's transpose); vrender is the fused V-Render
of a whole image."""
from .binning import RasterPlan, bin_and_sort, host_sort, radix_sorter, sort_pairs
from .blend import (blend_backward, blend_backward_alpha, blend_forward, prepare_backward, scatters, splat_backward,
                    weight_grads, work_groups)
from .project import project, tile_grid
from .select import Selection, check_pixels, check_sampler, select
from .sh import sh_colors
from .transpose import Transpose, backward_order, transpose
from .vrender import render_fused

__all__ = ["RasterPlan", "Selection", "Transpose", "backward_order", "bin_and_sort", "blend_backward",
           "blend_backward_alpha", "blend_forward", "check_pixels", "check_sampler", "host_sort", "prepare_backward",
           "project", "radix_sorter", "render_fused", "scatters", "select", "sh_colors", "sort_pairs",
           "splat_backward", "tile_grid", "transpose", "weight_grads", "work_groups"]
