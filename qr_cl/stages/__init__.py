"""The pipeline stages, one module per kernel file, each beside its numpy twin (``*_ref``):
project -> binning (RasterPlan) -> sh (colour) -> select (Selection) -> blend (and backward);
vrender is the fused V-Render of a whole image."""
from .binning import RasterPlan, bin_and_sort
from .blend import blend_backward, blend_forward, prepare_backward
from .project import project, tile_grid
from .select import Selection, check_pixels, check_sampler, select, transmittance_profile
from .sh import sh_colors
from .vrender import render_fused

__all__ = ["RasterPlan", "Selection", "bin_and_sort", "blend_backward", "blend_forward",
           "check_pixels", "check_sampler", "prepare_backward", "project", "render_fused", "select", "sh_colors",
           "tile_grid", "transmittance_profile"]
