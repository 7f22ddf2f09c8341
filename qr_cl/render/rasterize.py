"""The public renderer in qr-cl's conventions, the fused V-Render and the public plan call.

:func:`rasterize` renders one camera through a stored Selection (any sampler, pixel subsets, a
selection cache), an adapter over :func:`qr_cl.render.engine.render_view` (which
:func:`qr_cl.rasterization` adapts to gsplat's conventions); :func:`render_volume_fused` is the
fused V-Render kernel (whole images, no gradients, expected depth). Both take the same scene and
camera arguments, and render on the runtime whose device passed the render check
(:func:`qr_cl.render.selfcheck.checked_runtime`), as :func:`rasterize_plan` does by default.
"""
from __future__ import annotations

import numpy as np
import torch

from ..runtime import DEFAULTS, Runtime
from ..stages import RasterPlan, check_pixels, check_sampler
from .autograd import View
from .cache import SelectionCache
from .engine import background_tensor, feature_tensor, fused_volume, gaussian_tensors, render_view, sh_colors
from .meta import RenderMeta
from .plan import make_plan
from .selfcheck import checked_runtime


def rasterize_plan(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
                   viewmat: np.ndarray, K: np.ndarray, width: int, height: int,
                   near: float = 0.01, far: float = 1e10, rt: Runtime | None = None) -> RasterPlan:
    """Project, bin and sort Gaussians for one camera (geometry only).

    means [N,3], quats [N,4] unit w,x,y,z, scales [N,3] activated, opacities [N] activated (float32
    host arrays, N >= 1); viewmat [4,4] world-to-camera; K [3,3] intrinsics in px; width/height in px.
    Without ``rt``, the process's runtime, whose device has passed the render check.
    """
    return make_plan(rt or checked_runtime(), means, quats, scales, opacities, viewmat, K, width, height, near, far)


def camera(viewmat, K) -> tuple[np.ndarray, np.ndarray]:
    """viewmat [4,4] and K [3,3] as float32 numpy arrays (tensors are detached); ValueError naming
    a bad shape."""
    out = []
    for x, name, shape in ((viewmat, "viewmat", (4, 4)), (K, "K", (3, 3))):
        a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
        if a.shape != shape:
            raise ValueError(f"{name} has shape {tuple(a.shape)}, expected {shape}")
        out.append(np.ascontiguousarray(a, np.float32))
    return out[0], out[1]


def color_features(features, sh_degree: int | None, means: torch.Tensor, viewmat: np.ndarray,
                   rt: Runtime) -> torch.Tensor:
    """The color stage of qr-cl's calls: features [N,C] as given, or RGB [N,3] from SH
    coefficients [N,K,3] when ``sh_degree`` is set (by sh.cl on ``rt``)."""
    if sh_degree is None:
        return feature_tensor(features, means.shape[0])
    return sh_colors(features, means, viewmat, sh_degree, rt)


def empty_meta() -> dict:
    """The meta of a render of no Gaussians: the keys of a plan's meta, empty."""
    return {"means2d": np.zeros((0, 2), np.float32), "conics": np.zeros((0, 3), np.float32),
            "opacities": np.zeros(0, np.float32), "depths": np.zeros(0, np.float32),
            "radii": np.zeros((0, 2), np.int32), "tile_ranges": np.zeros((0, 2), np.int32),
            "flatten_ids": np.zeros(0, np.int32), "n_keys": 0}


def rasterize(means, quats, scales, opacities, features, viewmat, K, width: int, height: int,
              sampler: str = DEFAULTS.rasterize_sampler, k: int = DEFAULTS.k, sh_degree: int | None = None,
              near: float = 0.01, far: float = 1e10, background=None, pixels=None,
              cache: SelectionCache | None = None):
    """Render C-dim features (or RGB from SH) of 3D Gaussians for one pinhole camera through a
    Selection: plan (project, bin/sort) -> select (``sampler``) -> blend.

    Args:
        means [N,3], quats [N,4] w,x,y,z (normalised here), scales [N,3] activated (world units),
        opacities [N] activated in [0,1]: torch float32 CPU tensors (numpy arrays work too).
        features: [N,C] per-Gaussian features, C in 1..2048; or, with ``sh_degree`` set,
            SH coefficients [N,(d+1)^2,3] (d >= sh_degree; the first (sh_degree+1)^2 are used)
            evaluated per view into RGB (the color stage, as gsplat's ``colors`` with ``sh_degree``).
            C-contiguous float32 rows of a multiple of 16 channels are read in place on CPU
            devices; rows starting on a 64-byte line (torch's tensors) read fastest. A float16
            table (torch or numpy) is read as half and blended in float32: half the memory and
            bytes read, the image within float16 rounding of the float32 table's; its gradient
            is float16.
        viewmat: [4,4] world-to-camera (OpenCV axes: x right, y down, z forward).
        K: [3,3] intrinsics in pixels. width, height: image size in pixels.
        sampler: "volume" (full alpha blending, V-Render), "quantile" (Q-Render, Algorithm 1 with
            K = ``k``), "topk" (the ``k`` largest V-Render weights, blended as Q-Render does) or
            "stratified" (Stratified-K, App. E: Algorithm 1 with boundaries at the quantiles of a
            normal fitted to the ray's transmittance; see :mod:`qr_cl.stages.select`).
            For the fused V-Render kernel (no stored selection) call :func:`render_volume_fused`.
        near, far: depth culling planes (camera z, world units).
        background: [C] blended with the background weight of each ray, or None (black): the
            remaining transmittance for volume; for the K samplers (whose normalized weights sum
            to 1) it shows only through rays that selected no Gaussian.
        pixels: None (the whole image) or [P,2] integer (x, y) pixel coordinates: render only those
            rays (cost proportional to P).
        cache: an optional :class:`qr_cl.render.SelectionCache`: the Selection (and its
            RasterPlan) of the same geometry, camera, sampler, K and rays is then reused instead
            of recomputed.

    Returns:
        render [H,W,C] (or [P,C] for ``pixels``) float32 (float64 for float64 features), alpha [H,W,1] (or [P,1]): 1 - the
        transmittance where the ray's walk stopped (for quantile the walk stops once T < 1/(K+1)),
        and a meta mapping (a :class:`qr_cl.render.meta.RenderMeta`: host copies made on first
        access; a dict for no Gaussians) with means2d [N,2] (px), conics [N,3], depths [N] (camera
        z), radii [N,2] int32 (x, y half-extents in px; 0 = culled), opacities [N], tile_ranges
        [tiles,2], flatten_ids, n_keys and (for N >= 1) the ``selection`` used (:class:`qr_cl.stages.select.Selection`; a list of them,
        one per set of rays, when the render was split to fit the device's buffers).

        Renders larger than the device's largest buffer are split into sets of rays (the same
        image) and feature tables into row parts, each read in place (the same image to float
        rounding: the parts' blends are added); a render that still does not fit raises
        :class:`qr_cl.runtime.BufferLimitError` naming the sizes; a
        render whose host memory the system does not have available raises
        :class:`qr_cl.runtime.HostMemoryError`, also naming them.

        Compositing RGB from "quantile" (and "topk"/"stratified"): the selected weights are
        normalized to sum to 1, so the image is the color *given* a hit; faint edges and
        floaters come out opaque (halos). Multiply it by V-Render's alpha (``sampler="volume"``
        or :func:`render_volume_fused`: 1 - final T) before compositing; the alpha a K sampler
        returns itself (1 - T where its walk stopped) needs no second walk and is a little
        worse. ``qr-cl reproduce`` measures and pictures this.

        The render is differentiable (tensors with requires_grad) w.r.t. ``features`` (or the
        SH coefficients), ``background`` and the Gaussians (means, quats, scales, opacities),
        through the engine :func:`qr_cl.render.engine.render_view`, the one under
        :func:`qr_cl.rasterization` too. viewmat and K get no gradient.
    """
    k = check_sampler(sampler, k)
    if pixels is not None:
        pixels = check_pixels(pixels, width, height)
    gaussians = gaussian_tensors(means, quats, scales, opacities)
    viewmat, K = camera(viewmat, K)
    rt = checked_runtime()
    feats = color_features(features, sh_degree, gaussians[0], viewmat, rt)
    bg = background_tensor(background, feats.shape[1])
    out = render_view(*gaussians, feats, bg, View(viewmat, K, int(width), int(height), near, far, sampler, k, pixels),
                      cache, rt=rt)
    shape = (height, width) if pixels is None else (len(pixels),)
    image, alpha = out.image.reshape(*shape, feats.shape[1]), out.alpha.reshape(*shape, 1)
    if out.plan is None:
        return image, alpha, empty_meta()
    return image, alpha, RenderMeta(out.plan, selection=out.selections[0] if len(out.selections) == 1
                                    else out.selections)


def render_volume_fused(means, quats, scales, opacities, features, viewmat, K, width: int, height: int,
                        sh_degree: int | None = None, near: float = 0.01, far: float = 1e10,
                        background=None):
    """V-Render of a whole image in one fused kernel (no stored selection, no gradients): the
    same weights and summation order as ``rasterize(..., sampler="volume")``, the same image.

    Arguments as :func:`rasterize`. Returns image [H,W,C], alpha [H,W,1] (1 - T) and a meta mapping
    (as :func:`rasterize`'s) with the plan's keys (means2d, conics, depths, radii, opacities,
    tile_ranges, flatten_ids, n_keys) and ``depth`` [H,W,1], the expected depth (camera z; 0
    where nothing was hit). A feature table larger than the device's largest buffer is rendered a
    row part at a time (a walk per part, their blends added: the same image to float rounding).
    """
    gaussians = gaussian_tensors(means, quats, scales, opacities)
    viewmat, K = camera(viewmat, K)
    rt = checked_runtime()
    with torch.no_grad():
        feats = color_features(features, sh_degree, gaussians[0], viewmat, rt)
    bg = background_tensor(background, feats.shape[1])
    channels = feats.shape[1]
    if gaussians[0].shape[0] == 0:
        image = (torch.zeros(channels) if bg is None else bg).expand(height, width, channels).clone()
        alpha = torch.zeros(height, width, 1)
        return image, alpha, {**empty_meta(), "depth": alpha.numpy().copy()}
    image, alpha, plan, depth = fused_volume(rt, *gaussians, feats, bg, viewmat, K, width, height, near, far)
    return image, alpha, RenderMeta(plan, depth=depth)
