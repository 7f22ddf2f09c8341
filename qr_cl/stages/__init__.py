"""The pipeline stages, one module per kernel file, each but transpose beside its float64 twin
(``*_ref``): project -> binning (RasterPlan) -> sh (color) -> select (Selection) -> blend (and
backward: a scatter, or a gather over the selection's transpose); vrender is the fused V-Render
of a whole image."""
from .binning import PLAN_META_KEYS, RasterPlan, bin_and_sort, host_sort, radix_sorter, sort_pairs
from .blend import (BackwardIndex, blend_backward, blend_backward_alpha, blend_forward, prepare_backward, rows_to_half,
                    scatters, splat_backward, weight_grads, work_groups)
from .project import project, project_backward, tile_grid
from .select import Selection, SelectionKernel, check_pixels, check_sampler, deferred_select, entry_bytes, select
from .sh import sh_backward, sh_colors
from .transpose import Transpose, backward_order, transpose
from .vrender import render_fused

__all__ = ["BackwardIndex", "PLAN_META_KEYS", "RasterPlan", "Selection", "SelectionKernel", "Transpose",
           "backward_order", "bin_and_sort", "blend_backward", "blend_backward_alpha", "blend_forward", "check_pixels",
           "check_sampler", "deferred_select", "entry_bytes", "host_sort", "prepare_backward", "project",
           "project_backward", "radix_sorter", "render_fused", "rows_to_half", "scatters", "select", "sh_backward",
           "sh_colors", "sort_pairs", "splat_backward", "tile_grid", "transpose", "weight_grads", "work_groups"]
