"""The public, gsplat-style entry point: :func:`rasterize`."""
from __future__ import annotations

import numpy as np
import torch

from .autograd import blend
from .blend import blend_forward
from .device import runtime
from .raster import rasterize_plan, to_device
from .samplers import SelectionCache, check_pixels, select, selection_key
from .vrender import channel_layout, padded_rows, render_fused, sh_colors

SAMPLERS = ("volume", "quantile", "topk", "volume_fused")


def _host(x, name: str, shape: tuple) -> np.ndarray:
    """A float32 numpy view/copy of a tensor or array, with its shape checked (-1 = any)."""
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    if a.ndim != len(shape) or any(s != -1 and s != d for s, d in zip(shape, a.shape)):
        raise ValueError(f"{name} has shape {tuple(a.shape)}, expected {tuple('N' if s == -1 else s for s in shape)}")
    return np.ascontiguousarray(a, np.float32)


def rasterize(means, quats, scales, opacities, features, viewmat, K, width: int, height: int,
              sampler: str = "volume", k: int = 40, sh_degree: int | None = None,
              near: float = 0.01, far: float = 1e10, background=None, pixels=None,
              cache: SelectionCache | None = None):
    """Render C-dim features (or RGB from SH) of 3D Gaussians for one pinhole camera.

    Args:
        means [N,3], quats [N,4] unit w,x,y,z, scales [N,3] activated (world units),
        opacities [N] activated in [0,1]: torch float32 CPU tensors (numpy arrays work too).
        features: [N,C] per-Gaussian features, C in 1..2048; or, with ``sh_degree`` set,
            SH coefficients [N,(d+1)^2,3] (d >= sh_degree; the first (sh_degree+1)^2 are used)
            evaluated per view into RGB.
        viewmat: [4,4] world-to-camera (OpenCV axes: x right, y down, z forward).
        K: [3,3] intrinsics in pixels. width, height: image size in pixels.
        sampler: "volume" (full alpha blending, V-Render), "quantile" (Q-Render, Algorithm 1 with
            K = ``k``), "topk" (the ``k`` largest V-Render weights, blended as Q-Render does) or
            "volume_fused" (V-Render in one fused kernel, whole image only, no gradients). "volume"
            of a whole image whose features need no gradient runs the fused kernel too (same
            weights, same summation order, same image); otherwise rendering is select -> blend.
        near, far: depth culling planes (camera z, world units).
        background: [C] blended with the background weight of each ray, or None (black): the
            remaining transmittance for volume; for quantile/topk (whose normalized weights sum
            to 1) it shows only through rays that selected no Gaussian.
        pixels: None (the whole image) or [P,2] integer (x, y) pixel coordinates: render only those
            rays (cost proportional to P).
        cache: an optional :class:`qr_cl.samplers.SelectionCache`: the Selection (and its
            RasterPlan) of the same geometry, camera, sampler, K and rays is then reused instead
            of recomputed (not used by the fused path).

    Returns:
        render [H,W,C] (or [P,C] for ``pixels``) float32, alpha [H,W,1] (or [P,1]): 1 - the
        transmittance where the ray's walk stopped (for quantile the walk stops once T < 1/(K+1)),
        and a meta dict with means2d [N,2] (px), conics [N,3], depths [N] (camera z), radii [N]
        int32 (0 = culled), opacities [N], tile_ranges [tiles,2], n_keys, and either depth [H,W,1]
        (expected depth; fused path) or selection (the :class:`qr_cl.samplers.Selection` used).

        The render is differentiable w.r.t. ``features`` (a [N,C] tensor with requires_grad) and
        ``background`` through :class:`qr_cl.autograd.BlendFunction`. No gradient is produced for
        means, quats, scales, opacities, viewmat or K (the Gaussians are frozen in GS-Net), nor for
        SH coefficients (``sh_degree`` set).
    """
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler={sampler!r}: available samplers are {SAMPLERS}")
    if sampler in ("quantile", "topk") and (isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1):
        raise ValueError(f"k must be an integer >= 1 for sampler={sampler!r}, got {k!r}")
    if pixels is not None:
        if sampler == "volume_fused":
            raise ValueError("sampler='volume_fused' renders whole images; use 'volume' with pixels")
        pixels = check_pixels(pixels, width, height)
    means = _host(means, "means", (-1, 3))
    n = len(means)
    quats = _host(quats, "quats", (n, 4))
    scales = _host(scales, "scales", (n, 3))
    opacities = _host(opacities, "opacities", (n,))
    viewmat = _host(viewmat, "viewmat", (4, 4))
    K = _host(K, "K", (3, 3))
    if sh_degree is not None:
        sh = _host(features, "features (SH coefficients)", (n, -1, 3))
        if sh.shape[1] < (sh_degree + 1) ** 2:
            raise ValueError(f"sh_degree={sh_degree} needs {(sh_degree + 1) ** 2} coefficients per "
                             f"Gaussian, features have {sh.shape[1]}")
        sh = np.ascontiguousarray(sh[:, :(sh_degree + 1) ** 2])
        channels = 3
    else:
        feats = _host(features, "features", (n, -1))
        channels = feats.shape[1]
        if not 1 <= channels <= 2048:
            raise ValueError(f"features have {channels} channels; 1..2048 are supported")
    if n == 0:
        bg = np.zeros(channels, np.float32) if background is None else _host(background, "background", (channels,))
        shape = (height, width) if pixels is None else (len(pixels),)
        render = np.broadcast_to(bg, (*shape, channels)).copy()
        zeros = np.zeros((*shape, 1), np.float32)
        meta = {"means2d": np.zeros((0, 2), np.float32), "conics": np.zeros((0, 3), np.float32),
                "depths": np.zeros(0, np.float32), "radii": np.zeros(0, np.int32),
                "opacities": np.zeros(0, np.float32), "n_keys": 0, "depth": zeros}
        return torch.from_numpy(render), torch.from_numpy(zeros.copy()), meta

    rt = runtime()
    bg = None if background is None else _host(background, "background", (channels,))
    wants_grad = sh_degree is None and torch.is_grad_enabled() and any(
        isinstance(t, torch.Tensor) and t.requires_grad for t in (features, background))
    fused = sampler == "volume_fused" or (sampler == "volume" and pixels is None and not wants_grad)

    def make_selection():
        plan = rasterize_plan(means, quats, scales, opacities, viewmat, K, width, height, near, far, rt)
        return select(plan, sampler, k, pixels)
    if fused:
        plan = rasterize_plan(means, quats, scales, opacities, viewmat, K, width, height, near, far, rt)
    elif cache is not None:
        sel = cache.get(selection_key(means, quats, scales, opacities, viewmat, K, width, height, near,
                                      far, sampler, k, pixels), make_selection)
        plan = sel.plan
    else:
        sel = make_selection()
        plan = sel.plan
    if sh_degree is not None:
        campos = -viewmat[:3, :3].T @ viewmat[:3, 3]
        device_features = sh_colors(rt, to_device(rt, means), sh, campos)
    elif fused or not wants_grad:
        device_features = to_device(rt, padded_rows(feats, channel_layout(channels)[2]))
    meta = plan.meta()
    if fused:
        image, alpha, depth = render_fused(plan, device_features, channels, bg)
        meta["depth"] = depth
        return torch.from_numpy(image), torch.from_numpy(alpha), meta

    meta["selection"] = sel
    if wants_grad:
        tensor_bg = background if isinstance(background, torch.Tensor) else (
            None if bg is None else torch.from_numpy(bg))
        tensor_features = features if isinstance(features, torch.Tensor) else torch.from_numpy(feats)
        render = blend(sel, tensor_features, tensor_bg)
    else:
        rows = blend_forward(sel, device_features, channels, bg).get()[:, :channels]
        render = torch.from_numpy(np.ascontiguousarray(rows))
    alpha = torch.from_numpy(1 - sel.t_walk.get()[:sel.n_rays, None])
    if pixels is None:
        render, alpha = render.reshape(height, width, channels), alpha.reshape(height, width, 1)
    return render, alpha, meta
