"""The pipeline stages, one module per kernel file, each but transpose beside its float64 twin
(``*_ref``): project -> binning (RasterPlan) -> sh (color) -> select (Selection; and selections
made from selections) -> blend (select_and_blend: the selection with its first blend fused in;
and backward: a scatter, or a gather over the selection's transpose); vrender is the fused
V-Render of a whole image."""
from .binning import PLAN_META_KEYS, RasterPlan, bin_and_sort, host_sort, radix_sorter, sort_pairs
from .blend import (BackwardIndex, blend_backward, blend_backward_alpha, blend_forward, prepare_backward, rows_to_half,
                    scatters, select_and_blend, splat_backward, weight_grads, work_groups)
from .project import project, project_backward, tile_grid
from .select import Selection, check_pixels, check_sampler, entry_bytes, select
from .selections import (compact_selections, concat_selections, derived, gather_rays, listed_selection, ray_entries,
                         remap_ids)
from .sh import sh_backward, sh_colors
from .transpose import Transpose, backward_order, transpose
from .vrender import render_fused

__all__ = ["BackwardIndex", "PLAN_META_KEYS", "RasterPlan", "Selection", "Transpose", "backward_order", "bin_and_sort",
           "blend_backward", "blend_backward_alpha", "blend_forward", "check_pixels", "check_sampler",
           "compact_selections", "concat_selections", "derived", "entry_bytes", "gather_rays", "host_sort",
           "listed_selection", "prepare_backward", "project", "project_backward", "radix_sorter", "ray_entries",
           "remap_ids", "render_fused", "rows_to_half", "scatters", "select", "select_and_blend", "sh_backward",
           "sh_colors", "sort_pairs", "splat_backward", "tile_grid", "transpose", "weight_grads", "work_groups"]
