"""The rendering engine under both public calls: one camera, plan -> select -> blend, with
gradients w.r.t. the features, the background and the Gaussians (through gsplat's 2-D tensors:
:class:`~qr_cl.render.autograd.ProjectFunction` -> :class:`~qr_cl.render.autograd.RasterFunction`).

:func:`qr_cl.rasterize` and :func:`qr_cl.rasterization` are adapters of their argument conventions
over :func:`render_view`; both therefore check inputs the same way (:func:`gaussian_tensors`),
color from SH by the same kernel (:func:`sh_colors`), and split renders that exceed the
device's largest buffer into sets of rays the same way (feature tables larger than a buffer are
taken in row parts by the blend itself: :mod:`qr_cl.render.autograd`).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..runtime import (BufferLimitError, Runtime, channel_layout, check_buffer, check_channels, host_empty, table_parts,
                       trim_device_pool)
from ..stages import BackwardIndex, RasterPlan, Selection, render_fused
from .autograd import AbsGradSink, ProjectFunction, RasterFunction, SHColors, View
from .cache import SelectionCache, selection_key
from .plan import make_plan
from .rays import host_rows, image_pixels, ray_sets, select_and_blend_rays, table_rows


def _tensor(x) -> torch.Tensor:
    """x as a float32 CPU tensor (a tensor keeps its graph; numpy arrays are wrapped)."""
    t = x if isinstance(x, torch.Tensor) else torch.from_numpy(np.ascontiguousarray(x, np.float32))
    return t.to("cpu", torch.float32)


def gaussian_tensors(means, quats, scales, opacities) -> tuple[torch.Tensor, ...]:
    """The Gaussians as float32 CPU tensors (numpy arrays or tensors; graphs kept): means [N,3],
    quats [N,4] w,x,y,z (normalised here: they need not be unit), scales [N,3], opacities [N].
    ValueError naming the first bad shape."""
    t = [_tensor(x) for x in (means, quats, scales, opacities)]
    n = t[0].shape[0] if t[0].ndim == 2 else -1
    for x, name, shape in zip(t, ("means", "quats", "scales", "opacities"), ((n, 3), (n, 4), (n, 3), (n,))):
        if tuple(x.shape) != shape or n < 0:
            raise ValueError(f"{name} has shape {tuple(x.shape)}, expected "
                             f"{tuple('N' if d == n else d for d in shape)} (N Gaussians, from means [N, 3])")
    t[1] = t[1] / t[1].norm(dim=-1, keepdim=True)
    return tuple(t)


def feature_tensor(features, n: int) -> torch.Tensor:
    """features [N,C] (C in 1..MAX_CHANNELS) as a CPU tensor: a float tensor keeps its dtype, a
    float16 numpy array stays float16 (a half table: read as half, blended in float32), anything
    else becomes float32; the render returns their dtype, at least float32. ValueError otherwise."""
    if isinstance(features, np.ndarray) and features.dtype == np.float16:
        features = torch.from_numpy(features)
    f = features.to("cpu") if isinstance(features, torch.Tensor) and features.is_floating_point() \
        else _tensor(features)
    if f.ndim != 2 or f.shape[0] != n:
        raise ValueError(f"features has shape {tuple(f.shape)}, expected ({n}, C)")
    check_channels(f.shape[1])
    return f


def background_tensor(background, channels: int) -> torch.Tensor | None:
    """background [C] as a float32 tensor, or None; ValueError for another shape."""
    if background is None:
        return None
    bg = _tensor(background)
    if tuple(bg.shape) != (channels,):
        raise ValueError(f"background has shape {tuple(bg.shape)}, expected ({channels},)")
    return bg


def camera_centre(viewmat: np.ndarray | torch.Tensor) -> torch.Tensor:
    """The camera centre [3] (world) of a world-to-camera viewmat [4,4], -R^T t: a tensor viewmat
    keeps its graph."""
    view = viewmat if isinstance(viewmat, torch.Tensor) else torch.from_numpy(np.asarray(viewmat, np.float32))
    return -(view[:3, :3].T @ view[:3, 3])


def sh_colors(sh, means: torch.Tensor, viewmat: np.ndarray | torch.Tensor, sh_degree: int,
              rt: Runtime) -> torch.Tensor:
    """The color stage: view-dependent RGB [N,3] from SH coefficients [N,K,3] (the first
    (sh_degree+1)^2 of K, sh_degree <= 3) by sh.cl on ``rt``, differentiable w.r.t. the
    coefficients, the means and (a tensor viewmat [4,4]) the camera (gsplat's convention:
    max(SH(dir) . c + 0.5, 0), dir from the camera centre)."""
    sh = _tensor(sh)
    need = (sh_degree + 1) ** 2
    if sh.ndim != 3 or sh.shape[0] != means.shape[0] or sh.shape[2] != 3 or sh.shape[1] < need or sh_degree > 3:
        raise ValueError(f"sh_degree={sh_degree} needs SH coefficients [N, K >= {need}, 3] (sh_degree <= 3), "
                         f"got {tuple(sh.shape)}")
    if sh.shape[0] == 0:
        return sh.new_zeros(0, 3)
    return SHColors.apply(means, sh[:, :need], camera_centre(viewmat), rt)


@dataclass
class Render:
    """What :func:`render_view` returns: image [P,C] and alpha [P,1] tensors (P = H*W, row-major,
    or the view's pixels), the plan (None for no Gaussians), the selections of the ray sets and
    the blend of the extra signals [P,F] through the same selections (None without)."""

    image: torch.Tensor
    alpha: torch.Tensor
    plan: RasterPlan | None
    selections: list[Selection]
    extra: torch.Tensor | None = None


@dataclass
class Splats2D:
    """One camera's 2-D stage, what :class:`~qr_cl.render.autograd.RasterFunction` differentiates:
    the plan, and the values of its splats as tensors (graph nodes whose gradients are wanted;
    None for none): means2d [N,2] px, conics [N,3], opacities [N]."""

    plan: RasterPlan
    means2d: torch.Tensor | None
    conics: torch.Tensor | None
    opacities: torch.Tensor


def project_view(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                 views: list[View], viewmats: torch.Tensor | None = None, plans: list[RasterPlan] | None = None,
                 rt: Runtime | None = None) -> tuple[list[RasterPlan], torch.Tensor, torch.Tensor, torch.Tensor]:
    """The projection of C cameras as gsplat's tensors: (plans, means2d [C,N,2] px, conics [C,N,3],
    depths [C,N] camera z; zeros for culled Gaussians) of the Gaussians (N >= 1, unit quats,
    activated opacities [N]) for ``views``, differentiable w.r.t. means, quats, scales and
    ``viewmats`` (a [C,4,4] tensor with the views' values; None = no camera gradient).
    ``plans``: the views' projections if already made (their splats are read), else they are, on
    ``rt``."""
    plans = plans or [make_plan(rt, *(host_rows(t) for t in (means, quats, scales, opacities)), view.viewmat,
                                view.K, view.width, view.height, view.near, view.far) for view in views]
    view_t = torch.from_numpy(np.stack([view.viewmat for view in views])) if viewmats is None else viewmats
    return (plans, *ProjectFunction.apply(means, quats, scales, view_t, plans, views))


def _grad_wanted(*tensors: torch.Tensor | None) -> bool:
    """Whether autograd records and one of the tensors (None: absent) requires a gradient."""
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def render_view(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                features: torch.Tensor, background: torch.Tensor | None, view: View,
                cache: SelectionCache | None = None, viewmat: torch.Tensor | None = None,
                splats: Splats2D | None = None, absgrad: AbsGradSink | None = None,
                extra: torch.Tensor | None = None, *, rt: Runtime) -> Render:
    """Render features [N,C] of the Gaussians (from :func:`gaussian_tensors`, unit quats) for
    ``view``: plan, then per set of rays (:func:`ray_sets`) select and blend through
    :class:`~qr_cl.render.autograd.RasterFunction` (in row parts where the table exceeds a device
    buffer), so gradients reach features, background, Gaussians and ``viewmat`` (a [4,4] tensor
    with view.viewmat's values, or None: no camera gradient). ``cache`` reuses the selections of the
    same geometry, camera, sampler, K and rays.

    ``extra``: [N,F] signals blended through the same selections (one plan, one walk per ray; a
    blend of their own, without background) into ``Render.extra``. ``splats``: the view's 2-D
    stage made by the caller (gsplat's meta tensors: the plan and tensors whose gradients the
    caller reads); by default it is made here from the first selection's plan, through
    :class:`~qr_cl.render.autograd.ProjectFunction` when a gradient w.r.t. the geometry is
    wanted. ``absgrad`` receives each blend's sums of |dL/dmean2d| [N,2] in the backward. ``rt``:
    the runtime to render on (the public calls pass the checked one: :mod:`qr_cl.render.selfcheck`).

    A selection made here (not found in ``cache``) is made with the first table's blend in one
    stage call (:func:`~qr_cl.render.rays.select_and_blend_rays`). Its backward index (transpose,
    owner bounds) is kept with it: in the cache's entry, or by the autograd Functions of this
    render."""
    n, channels = means.shape[0], features.shape[1]
    n_rays = view.width * view.height if view.pixels is None else len(view.pixels)
    if n == 0:
        bg = torch.zeros(channels) if background is None else background.detach()
        return Render(bg.expand(n_rays, channels).clone(), torch.zeros(n_rays, 1), None, [],
                      None if extra is None else torch.zeros(n_rays, extra.shape[1]))
    camera = _Camera((means, quats, scales, opacities), view, cache, viewmat, splats, rt)
    tables = [(features, background)] + ([] if extra is None else [(extra, None)])
    cstride = max(channel_layout(table.shape[1])[2] for table, _ in tables)
    parts: list[tuple[Selection, list[torch.Tensor], torch.Tensor]] = []
    for rays in ray_sets(rt, view.width, view.height, view.pixels, view.k, cstride):
        parts += _render_rays(camera, rays, tables, absgrad)
    trim_device_pool(rt)
    sels = [sel for sel, _, _ in parts]
    images = [parts[0][1][t] if len(parts) == 1 else torch.cat([p[1][t] for p in parts]) for t in range(len(tables))]
    alpha = parts[0][2] if len(parts) == 1 else torch.cat([p[2] for p in parts])
    return Render(images[0], alpha, sels[0].plan, sels, images[1] if extra is not None else None)


class _Camera:
    """What the ray sets of one :func:`render_view` share: the Gaussians (tensors, and their host
    rows), the view, the cache, the plan (made when first needed, unless the caller's ``splats``
    bring one) and the 2-D stage of the splats (made once, from the first selection's plan)."""

    def __init__(self, gaussians: tuple[torch.Tensor, ...], view: View, cache: SelectionCache | None,
                 viewmat: torch.Tensor | None, splats: Splats2D | None, rt: Runtime) -> None:
        self.gaussians, self.view, self.cache, self.viewmat, self.rt = gaussians, view, cache, viewmat, rt
        self.geometry = [host_rows(t) for t in gaussians]
        self.plan = None if splats is None else splats.plan
        self.splats = splats

    def planned(self) -> RasterPlan:
        """The view's plan (made now if it is not yet)."""
        if self.plan is None:
            view = self.view
            self.plan = make_plan(self.rt, *self.geometry, view.viewmat, view.K, view.width, view.height, view.near,
                                  view.far)
        return self.plan

    def key(self, rays: np.ndarray | None) -> str:
        """The cache key of the selection of ``rays``."""
        view = self.view
        return selection_key(*self.geometry, view.viewmat, view.K, view.width, view.height, view.near, view.far,
                             view.sampler, view.k, rays)

    def splats_of(self, plan: RasterPlan) -> Splats2D:
        """The 2-D stage of ``plan``'s splats (the first asked for serves every ray set), through
        :class:`~qr_cl.render.autograd.ProjectFunction` when a gradient w.r.t. the geometry is wanted."""
        if self.splats is None:
            means, quats, scales, opacities = self.gaussians
            means2d = conics = None
            if _grad_wanted(means, quats, scales, self.viewmat):
                _, means2d, conics, _ = project_view(means, quats, scales, opacities, [self.view],
                                                     None if self.viewmat is None else self.viewmat[None], [plan])
                means2d, conics = means2d[0], conics[0]
            self.splats = Splats2D(plan, means2d, conics, opacities)
        return self.splats


def fused_volume(rt: Runtime, means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor,
                 opacities: torch.Tensor, features: torch.Tensor, background: torch.Tensor | None,
                 viewmat: np.ndarray, K: np.ndarray, width: int, height: int, near: float = 0.01,
                 far: float = 1e10) -> tuple[torch.Tensor, torch.Tensor, RasterPlan, np.ndarray]:
    """The fused V-Render of a whole image on ``rt`` (:func:`qr_cl.render_volume_fused` once its
    arguments are checked): Gaussians from :func:`gaussian_tensors` (N >= 1), features [N,C] and
    background [C] or None tensors, viewmat [4,4] and K [3,3] float32, width/height in px. Returns
    image [H,W,C] and alpha [H,W,1] tensors, the plan and the expected depth [H,W,1]. A table
    larger than the device's largest buffer is rendered a row part at a time (their blends added)."""
    channels = features.shape[1]
    plan = make_plan(rt, *(host_rows(t) for t in (means, quats, scales, opacities)), viewmat, K, width, height, near,
                     far)
    cstride = channel_layout(channels)[2]
    check_buffer(rt, 4 * height * width * cstride, f"the fused V-Render image of {width}x{height} "
                 f"px x {cstride} channels (rasterize(..., sampler='volume') renders it in chunks)")
    table, out = table_rows(features), host_empty((height, width, cstride))
    for r0, rows in table_parts(rt, table, cstride):           # a table beyond a buffer: row parts
        image, alpha, depth = render_fused(plan, rows, channels, None if r0 or background is None else
                                           background.numpy(), out=out, row0=r0, accumulate=r0 > 0)
    trim_device_pool(rt)
    return torch.from_numpy(image), torch.from_numpy(alpha), plan, depth


def _render_rays(camera: _Camera, rays: np.ndarray | None, tables: list[tuple],
                 absgrad: AbsGradSink | None) -> list[tuple]:
    """(Selection, [image [P,C] of each feature table], alpha [P,1]) of the rays ``rays`` (None =
    the whole image), tables being (features [N,C], background [C] or None): one entry, or several
    when a selection does not fit in a device buffer and the rays are halved. The selection is
    the cache's, or made with the first table's blend (and then cached)."""
    view, cache = camera.view, camera.cache
    key = None if cache is None else camera.key(rays)
    found = None if cache is None else cache.find(key)
    image = None
    try:
        if found is None:
            sel, image = select_and_blend_rays(camera.planned(), view.sampler, max(view.k, 1), rays, *tables[0])
            backward_index = BackwardIndex() if cache is None else cache.keep(key, sel)
        else:
            sel, backward_index = found
    except BufferLimitError:
        if rays is not None and len(rays) < 2:
            raise
        rays = image_pixels(view.width, view.height) if rays is None else rays
        half = len(rays) // 2
        return _render_rays(camera, rays[:half], tables, absgrad) + _render_rays(camera, rays[half:], tables, absgrad)
    s2d = camera.splats_of(sel.plan)
    outs = [RasterFunction.apply(s2d.means2d, s2d.conics, s2d.opacities, features, background, sel, absgrad,
                                 backward_index, None if t else image)
            for t, (features, background) in enumerate(tables)]
    return [(sel, [image for image, _ in outs], outs[0][1])]
