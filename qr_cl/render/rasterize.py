"""The public renderers, as stages: colour -> plan (project, bin/sort) -> select -> blend.

:func:`rasterize` renders through a stored Selection (any sampler, pixel subsets, gradients w.r.t.
the features); :func:`render_volume_fused` is the fused V-Render kernel (whole images, no
gradients, expected depth). Both take the same scene and camera arguments.
"""
from __future__ import annotations

import numpy as np
import torch

from ..runtime import (BufferLimitError, Runtime, channel_layout, check_buffer, check_channels, device_rows,
                       host_empty, to_device, trim_device_pool)
from ..stages.binning import RasterPlan, RenderMeta
from ..stages.select import check_pixels, check_sampler, entry_bytes, select
from ..stages.sh import sh_colors
from ..stages.vrender import render_fused
from .autograd import blend
from .cache import SelectionCache, selection_key
from .plan import rasterize_plan
from .selfcheck import checked_runtime


def _host(x, name: str, shape: tuple) -> np.ndarray:
    """A float32 numpy view/copy of a tensor or array, with its shape checked (-1 = any)."""
    a = x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)
    if a.ndim != len(shape) or any(s != -1 and s != d for s, d in zip(shape, a.shape)):
        raise ValueError(f"{name} has shape {tuple(a.shape)}, expected {tuple('N' if s == -1 else s for s in shape)}")
    return np.ascontiguousarray(a, np.float32)


def channel_groups(rt: Runtime, n: int, channels: int) -> list[slice]:
    """Feature columns rendered together: all ``channels`` when their [n, cstride] device rows fit
    in one buffer of the device, else groups of a multiple of 16 channels that do (channels are
    blended independently, so the image is the same). BufferLimitError if 16 do not fit."""
    if 4 * n * channel_layout(channels)[2] <= rt.max_buffer_bytes:
        return [slice(0, channels)]
    per = rt.max_buffer_bytes // (4 * n) // 16 * 16
    if per < 16:
        check_buffer(rt, 4 * n * 16, f"features of {n} Gaussians x 16 channels (the smallest group)")
    return [slice(c, min(c + per, channels)) for c in range(0, channels, per)]


def image_pixels(width: int, height: int) -> np.ndarray:
    """Every pixel (x, y) of a width x height image, row-major: [H*W, 2] int32."""
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs.ravel(), ys.ravel()], 1).astype(np.int32)


def ray_sets(rt: Runtime, width: int, height: int, pixels: np.ndarray | None, k: int,
             cstride: int) -> list[np.ndarray | None]:
    """The rays of a render in sets whose image rows ([P, cstride] floats) and dense selection
    rows ([P, K], and their transpose's keys: :func:`entry_bytes`) fit in one device buffer: ``[pixels]`` when everything fits (None = the whole
    image), else consecutive runs of the pixel coordinates [P_i, 2] (x, y), row-major for the
    whole image, so concatenating the sets' rows gives the image."""
    n_rays = width * height if pixels is None else len(pixels)
    per_ray = max(4 * cstride, entry_bytes(rt) * k)
    if n_rays * per_ray <= rt.max_buffer_bytes:
        return [pixels]
    pixels = image_pixels(width, height) if pixels is None else pixels
    step = max(1, rt.max_buffer_bytes // per_ray)
    return [pixels[i:i + step] for i in range(0, n_rays, step)]


class _Scene:
    """The checked host arrays of one render call, with the colour stage applied: features [N,C]
    (a tensor when given one, so gradients can flow) or RGB from SH (``sh_degree`` set)."""

    def __init__(self, means, quats, scales, opacities, features, viewmat, K, sh_degree, background):
        self.means = _host(means, "means", (-1, 3))
        n = len(self.means)
        self.quats = _host(quats, "quats", (n, 4))
        self.scales = _host(scales, "scales", (n, 3))
        self.opacities = _host(opacities, "opacities", (n,))
        self.viewmat = _host(viewmat, "viewmat", (4, 4))
        self.K = _host(K, "K", (3, 3))
        if sh_degree is None:
            self.features = features if isinstance(features, torch.Tensor) else \
                torch.from_numpy(_host(features, "features", (n, -1)))
            if self.features.ndim != 2 or self.features.shape[0] != n:
                raise ValueError(f"features has shape {tuple(self.features.shape)}, expected (N, C)")
        else:
            self.features = torch.from_numpy(self._rgb_from_sh(features, sh_degree))
        self.channels = self.features.shape[1]
        check_channels(self.channels)
        self.background = background if background is None or isinstance(background, torch.Tensor) else \
            torch.from_numpy(_host(background, "background", (self.channels,)))
        if self.background is not None and tuple(self.background.shape) != (self.channels,):
            raise ValueError(f"background has shape {tuple(self.background.shape)}, expected ({self.channels},)")

    def _rgb_from_sh(self, features, sh_degree: int) -> np.ndarray:
        """The colour stage: view-dependent RGB [N,3] from SH coefficients [N,(d+1)^2,3]."""
        n = len(self.means)
        sh = _host(features, "features (SH coefficients)", (n, -1, 3))
        if sh.shape[1] < (sh_degree + 1) ** 2:
            raise ValueError(f"sh_degree={sh_degree} needs {(sh_degree + 1) ** 2} coefficients per "
                             f"Gaussian, features have {sh.shape[1]}")
        if n == 0:
            return np.zeros((0, 3), np.float32)
        rt = checked_runtime()
        campos = -self.viewmat[:3, :3].T @ self.viewmat[:3, 3]
        rgb = sh_colors(rt, to_device(rt, self.means), np.ascontiguousarray(sh[:, :(sh_degree + 1) ** 2]), campos)
        return rgb.get()[:, :3].copy()

    def plan(self, width: int, height: int, near: float, far: float) -> RasterPlan:
        return rasterize_plan(self.means, self.quats, self.scales, self.opacities, self.viewmat, self.K,
                              width, height, near, far)

    def empty(self, shape: tuple[int, ...]) -> tuple[torch.Tensor, torch.Tensor, dict]:
        """The render of no Gaussians: the background (black if None), alpha 0, and a meta with
        the keys of a non-empty render."""
        bg = torch.zeros(self.channels) if self.background is None else self.background.detach().float()
        zeros = np.zeros((*shape, 1), np.float32)
        meta = {"means2d": np.zeros((0, 2), np.float32), "conics": np.zeros((0, 3), np.float32),
                "opacities": np.zeros(0, np.float32), "depths": np.zeros(0, np.float32),
                "radii": np.zeros(0, np.int32), "tile_ranges": np.zeros((0, 2), np.int32),
                "flatten_ids": np.zeros(0, np.int32), "n_keys": 0}
        return bg.expand(*shape, self.channels).clone(), torch.from_numpy(zeros), meta


def rasterize(means, quats, scales, opacities, features, viewmat, K, width: int, height: int,
              sampler: str = "volume", k: int = 40, sh_degree: int | None = None,
              near: float = 0.01, far: float = 1e10, background=None, pixels=None,
              cache: SelectionCache | None = None):
    """Render C-dim features (or RGB from SH) of 3D Gaussians for one pinhole camera through a
    Selection: plan (project, bin/sort) -> select (``sampler``) -> blend.

    Args:
        means [N,3], quats [N,4] unit w,x,y,z, scales [N,3] activated (world units),
        opacities [N] activated in [0,1]: torch float32 CPU tensors (numpy arrays work too).
        features: [N,C] per-Gaussian features, C in 1..2048; or, with ``sh_degree`` set,
            SH coefficients [N,(d+1)^2,3] (d >= sh_degree; the first (sh_degree+1)^2 are used)
            evaluated per view into RGB (the colour stage, as gsplat's ``colors`` with ``sh_degree``).
            C-contiguous float32 rows of a multiple of 16 channels are read in place on CPU
            devices; rows starting on a 64-byte line (torch's tensors) read fastest: a large
            numpy array starts 16 bytes past one, which made the blend's row loads straddle
            lines (a 300k-Gaussian room's K=40 blend 330 against 238 ms on an AVX2 CPU).
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
        render [H,W,C] (or [P,C] for ``pixels``) float32, alpha [H,W,1] (or [P,1]): 1 - the
        transmittance where the ray's walk stopped (for quantile the walk stops once T < 1/(K+1)),
        and a meta mapping (a :class:`qr_cl.stages.binning.RenderMeta`: host copies made on first
        access; a dict for no Gaussians) with means2d [N,2] (px), conics [N,3], depths [N] (camera
        z), radii [N] int32 (0 = culled), opacities [N], tile_ranges [tiles,2], flatten_ids, n_keys and (for
        N >= 1) the ``selection`` used (:class:`qr_cl.stages.select.Selection`; a list of them,
        one per set of rays, when the render was split to fit the device's buffers).

        Renders larger than the device's largest buffer are split into sets of rays and groups
        of channels (the same image); features whose 16 channels alone do not fit, or a render
        that still does not fit, raise :class:`qr_cl.runtime.BufferLimitError` naming the sizes.

        Compositing RGB from "quantile" (and "topk"/"stratified"): the selected weights are
        normalized to sum to 1, so the image is the colour *given* a hit; faint edges and
        floaters come out opaque (halos), and the raw image gets worse with K (fox, 4 views at
        640x480: 22.1 / 21.5 / 21.0 dB PSNR from V-Render at K = 10 / 20 / 40). Multiply it by
        V-Render's alpha (``sampler="volume"`` or :func:`render_volume_fused`: 1 - final T)
        before compositing: 41.7 / 47.4 / 53.3 dB. The alpha a K sampler returns itself (1 - T
        where its walk stopped) needs no second walk and costs about 3 dB (38.6 / 44.5 /
        50.7 dB). ``qr-cl reproduce`` measures and pictures this.

        The render is differentiable w.r.t. ``features`` (a [N,C] tensor with requires_grad) and
        ``background`` through :class:`qr_cl.render.autograd.BlendFunction`. No gradient is
        produced for means, quats, scales, opacities, viewmat or K (the Gaussians are frozen in
        GS-Net), nor for SH coefficients (``sh_degree`` set): :func:`qr_cl.rasterization`
        renders with gradients w.r.t. the Gaussians.
    """
    k = check_sampler(sampler, k)
    if pixels is not None:
        pixels = check_pixels(pixels, width, height)
    scene = _Scene(means, quats, scales, opacities, features, viewmat, K, sh_degree, background)
    if len(scene.means) == 0:
        return scene.empty((height, width) if pixels is None else (len(pixels),))

    rt = checked_runtime()
    plans: list[RasterPlan] = []

    def selection(rays):
        def make():
            if not plans:
                plans.append(scene.plan(width, height, near, far))
            return select(plans[0], sampler, k, rays, defer=True)   # made by the first blend
        if cache is None:
            return make()
        return cache.get(selection_key(scene.means, scene.quats, scene.scales, scene.opacities, scene.viewmat,
                                       scene.K, width, height, near, far, sampler, k, rays), make)

    groups = channel_groups(rt, len(scene.means), scene.channels)
    parts = []
    for rays in ray_sets(rt, width, height, pixels, k, channel_layout(groups[0].stop - groups[0].start)[2]):
        parts += _render_rays(selection, rays, width, height, scene, groups)
    sels = [sel for sel, _, _ in parts]
    render = torch.cat([r for _, r, _ in parts]) if len(parts) > 1 else parts[0][1]
    alpha = torch.from_numpy(parts[0][2] if len(parts) == 1 else np.concatenate([a for _, _, a in parts]))
    meta = RenderMeta(sels[0].plan, selection=sels[0] if len(sels) == 1 else sels)
    if pixels is None:
        render, alpha = render.reshape(height, width, scene.channels), alpha.reshape(height, width, 1)
    trim_device_pool(rt)
    return render, alpha, meta


def _render_rays(selection, rays: np.ndarray | None, width: int, height: int, scene: _Scene,
                 groups: list[slice]) -> list[tuple]:
    """(Selection, render [P,C], alpha [P,1]) of the rays ``rays`` (None = whole image): one
    entry, or several when a selection does not fit in a device buffer and the rays are halved."""
    try:
        sel = selection(rays)
    except BufferLimitError:
        if rays is not None and len(rays) < 2:
            raise
        rays = image_pixels(width, height) if rays is None else rays
        half = len(rays) // 2
        return (_render_rays(selection, rays[:half], width, height, scene, groups)
                + _render_rays(selection, rays[half:], width, height, scene, groups))
    bg = scene.background
    try:
        cols = [blend(sel, scene.features[:, g], None if bg is None else bg[g]) for g in groups]
    finally:
        sel.ready()                          # made even if no blend ran (it may be cached)
    render = cols[0] if len(cols) == 1 else torch.cat(cols, 1)
    t_walk = sel.t_walk.get(ary=host_empty(sel.t_walk.shape, np.float32))
    alpha = np.subtract(1, t_walk[:sel.n_rays, None], out=host_empty((sel.n_rays, 1)))
    return [(sel, render, alpha)]


def render_volume_fused(means, quats, scales, opacities, features, viewmat, K, width: int, height: int,
                        sh_degree: int | None = None, near: float = 0.01, far: float = 1e10,
                        background=None):
    """V-Render of a whole image in one fused kernel (no stored selection, no gradients): the
    same weights and summation order as ``rasterize(..., sampler="volume")``, the same image.

    Arguments as :func:`rasterize`. Returns image [H,W,C], alpha [H,W,1] (1 - T) and a meta mapping
    (as :func:`rasterize`'s) with the plan's keys (means2d, conics, depths, radii, opacities, tile_ranges, flatten_ids,
    n_keys) and ``depth`` [H,W,1], the expected depth (camera z; 0 where nothing was hit).
    """
    scene = _Scene(means, quats, scales, opacities, features, viewmat, K, sh_degree, background)
    if len(scene.means) == 0:
        image, alpha, meta = scene.empty((height, width))
        return image, alpha, {**meta, "depth": alpha.numpy().copy()}
    plan = scene.plan(width, height, near, far)
    cstride = channel_layout(scene.channels)[2]
    bg = None if scene.background is None else scene.background.detach().cpu().numpy()
    feats = scene.features.detach().to("cpu", torch.float32).numpy()
    check_buffer(plan.runtime, 4 * height * width * cstride, f"the fused V-Render image of {width}x{height} "
                 f"px x {cstride} channels (rasterize(..., sampler='volume') renders it in chunks)")
    with device_rows(plan.runtime, feats, cstride) as rows:
        image, alpha, depth = render_fused(plan, rows, scene.channels, bg, out=host_empty((height, width, cstride)))
    trim_device_pool(plan.runtime)
    return torch.from_numpy(image), torch.from_numpy(alpha), RenderMeta(plan, depth=depth)
