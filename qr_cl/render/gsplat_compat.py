"""A gsplat-compatible, differentiable rasterizer: :func:`rasterization` takes gsplat's argument
names, shapes and conventions (batched cameras, SH or colors, render modes, backgrounds, packed or
dense meta) and returns what gsplat returns, with gradients w.r.t. the Gaussians, the cameras'
viewmats and gsplat's 2-D tensors (``meta["means2d"].grad``, ``.absgrad``: what densification
strategies read), and Q-Render / top-K as samplers; :func:`rasterize_top_contributing_gaussian_ids`
is gsplat's top-contributor query.

A gsplat call ports by changing the import::

    from gsplat import rasterization            ->   from qr_cl import rasterization

gsplat arguments that qr-cl does not implement raise a ValueError naming them (see
:data:`UNSUPPORTED`); none is ignored silently.
"""
from __future__ import annotations

import numpy as np
import torch

from ..runtime import ALPHA_MIN, SPLAT, SPLAT_FLOATS, TILE, device_zeros, to_device
from ..stages import RasterPlan, check_sampler, select
from .autograd import AbsGradSink, View
from .engine import Render, Splats2D, gaussian_tensors, project_view, render_view, sh_colors
from .selfcheck import checked_runtime

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")

#: gsplat arguments qr-cl accepts only at one value: name -> (the value, what to do instead).
UNSUPPORTED = {
    "radius_clip": (0.0, "qr-cl culls by near/far planes and opacity only"),
    "eps2d": (0.3, "the 2D low-pass is fixed at 0.3 px (3DGS)"),
    "tile_size": (TILE, f"the tile size is fixed at {TILE} px"),
    "sparse_grad": (False, "gradients are dense [N, ...] tensors"),
    "rasterize_mode": ("classic", "only 3DGS's classic alpha is implemented, not 'antialiased'"),
    "distributed": (False, "scale out with torch.distributed around the call"),
    "camera_model": ("pinhole", "only pinhole cameras are implemented"),
    "segmented": (False, "no segmented sort"),
    "covars": (None, "pass quats and scales, not covariances"),
    "with_ut": (False, "no unscented transform"),
    "with_eval3d": (False, "no 3D evaluation of the Gaussians"),
    "radial_coeffs": (None, "no lens distortion"),
    "tangential_coeffs": (None, "no lens distortion"),
    "thin_prism_coeffs": (None, "no lens distortion"),
    "ftheta_coeffs": (None, "no lens distortion"),
    "viewmats_rs": (None, "no rolling shutter"),
}


def _check_options(options: dict) -> None:
    def differs(value, default) -> bool:
        return value is not None if default is None else value != default
    bad = [f"{name}={value!r} ({UNSUPPORTED[name][1]}; only {UNSUPPORTED[name][0]!r} is supported)"
           for name, value in options.items() if differs(value, UNSUPPORTED[name][0])]
    if bad:
        raise ValueError("qr_cl.rasterization does not support: " + "; ".join(bad))


def _per_camera(x: torch.Tensor, n_cameras: int, ndim: int, name: str) -> list[torch.Tensor]:
    """x with ``ndim`` dims shared by every camera, or ndim + 1 dims with a leading [C]: one
    tensor per camera."""
    if x.ndim == ndim:
        return [x] * n_cameras
    if x.ndim == ndim + 1 and x.shape[0] == n_cameras:
        return list(x.unbind(0))
    raise ValueError(f"{name} has shape {tuple(x.shape)}: expected {ndim} dims, or {ndim + 1} with "
                     f"a leading camera dimension of {n_cameras}")


def _with_depth(background: torch.Tensor | None, render_mode: str) -> torch.Tensor | None:
    """A camera's background [D] for ``render_mode``: with a 0 for the depth channel (and only that
    for "D" and "ED")."""
    if background is None or render_mode == "RGB":
        return background
    color = background[:0] if render_mode in ("D", "ED") else background
    return torch.cat([color, background.new_zeros(1)])


def _absgrad_sink(target: torch.Tensor, rows: int | slice, ids: torch.Tensor | None) -> AbsGradSink:
    """A backward callback adding one camera's |dL/dmean2d| sums [N,2] into ``target.absgrad``
    (made as zeros the first time) at ``rows``: the camera's index in the dense [C,N,2] layout, or
    its rows of the packed [nnz,2] one, which hold its Gaussians ``ids``."""
    def add(sums: np.ndarray) -> None:
        if getattr(target, "absgrad", None) is None:
            target.absgrad = torch.zeros(target.shape, dtype=target.dtype)
        part = torch.from_numpy(np.ascontiguousarray(sums)).to(target.dtype)
        target.absgrad[rows] += part if ids is None else part[ids]
    return add


class _Rows(torch.autograd.Function):
    """rows [M,...] = x[index] of x [R,...] by indices [M] (a numpy gather: no torch kernel whose
    thread team would then compete with the OpenCL device's threads); the backward writes the
    rows' gradients into zeros, or, unless the indices are ``distinct``, adds them in index order
    (a repeated index sums its rows)."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, index: np.ndarray, distinct: bool):
        ctx.index, ctx.shape, ctx.distinct = index, x.shape, distinct
        return torch.from_numpy(x.detach().numpy()[index])

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        out = np.zeros(ctx.shape, np.float32)
        if ctx.distinct:
            out[ctx.index] = grad.numpy()
        else:
            np.add.at(out, ctx.index, grad.numpy())
        return torch.from_numpy(out).to(grad.dtype), None, None


class _Scatter(torch.autograd.Function):
    """x [R,...] = rows [M,...] at distinct indices [M], zeros elsewhere (numpy, as :class:`_Rows`,
    whose inverse it is); the backward gathers."""

    @staticmethod
    def forward(ctx, rows: torch.Tensor, index: np.ndarray, n: int):
        ctx.index = index
        out = np.zeros((n, *rows.shape[1:]), np.float32)
        out[index] = rows.detach().numpy()
        return torch.from_numpy(out).to(rows.dtype)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        return torch.from_numpy(grad.numpy()[ctx.index]), None, None


def _two_d(plans: list[RasterPlan] | None, means2d: torch.Tensor, conics: torch.Tensor, depths: torch.Tensor,
           opacities: torch.Tensor, packed: bool, absgrad: bool
           ) -> tuple[dict, list[Splats2D], torch.Tensor, list[AbsGradSink | None]]:
    """gsplat's 2-D meta tensors of the cameras' projections (plans, None for no Gaussians;
    means2d [C,N,2], conics [C,N,3], depths [C,N] from :func:`project_view`), dense [C,N,...] or
    packed [nnz,...], and what each camera's render reads from them: its :class:`Splats2D`, the
    depths [C,N] and the absgrad callbacks (or None): views or scatters of the meta tensors, so
    that their gradients (``meta["means2d"].grad`` after backward) are the sums of the cameras'
    renders."""
    n_cameras, n = means2d.shape[:2]
    radii = (np.stack([plan.radii.get() for plan in plans]) if plans is not None
             else np.zeros((n_cameras, n, 2), np.int32))
    if not packed:
        o = opacities.expand(n_cameras, n)
        meta = {"batch_ids": None, "camera_ids": None, "gaussian_ids": None, "radii": torch.from_numpy(radii),
                "means2d": means2d, "depths": depths, "conics": conics, "opacities": o}
        splats = [Splats2D(plan, means2d[c], conics[c], o[c]) for c, plan in enumerate(plans or [])]
        sinks = [_absgrad_sink(means2d, c, None) if absgrad else None for c in range(n_cameras)]
        return meta, splats, depths, sinks
    camera_ids, gaussian_ids = np.nonzero(radii[..., 0] > 0)
    flat = camera_ids * n + gaussian_ids
    m, c, d = (_Rows.apply(x.reshape(n_cameras * n, *x.shape[2:]), flat, True) for x in (means2d, conics, depths))
    o = _Rows.apply(opacities, gaussian_ids, n_cameras == 1)
    meta = {"batch_ids": torch.zeros(len(flat), dtype=torch.int64), "camera_ids": torch.from_numpy(camera_ids),
            "gaussian_ids": torch.from_numpy(gaussian_ids), "radii": torch.from_numpy(radii[camera_ids, gaussian_ids]),
            "means2d": m, "depths": d, "conics": c, "opacities": o}
    dense = [_Scatter.apply(x, flat, n_cameras * n).reshape(n_cameras, n, *x.shape[1:]) for x in (m, c, o, d)]
    splats = [Splats2D(plan, dense[0][i], dense[1][i], dense[2][i]) for i, plan in enumerate(plans or [])]
    bounds = np.searchsorted(camera_ids, np.arange(n_cameras + 1))      # the cameras' rows, in camera order
    rows = [slice(int(bounds[i]), int(bounds[i + 1])) for i in range(n_cameras)]
    sinks = [_absgrad_sink(m, r, torch.from_numpy(gaussian_ids[r])) if absgrad else None for r in rows]
    return meta, splats, dense[3], sinks


def _intersections(plans: list[RasterPlan] | None, depths: torch.Tensor, meta: dict, width: int,
                   height: int) -> dict:
    """gsplat's tile-intersection meta of the cameras' plans (None for no Gaussians) and depths
    [C,N] (:func:`project_view`): isect_offsets [C,tile_height,tile_width]
    int32 (each tile's first intersection in flatten_ids, an exclusive scan over cameras and tiles),
    flatten_ids [n_isects] int32 (per camera, tile and depth: camera * N + Gaussian in the dense
    layout, the packed row in the packed one), isect_ids [n_isects] int64 (camera << (32 +
    tile bits) | tile << 32 | the depth's float32 bits) and tiles_per_gauss ([C,N] or [nnz] int32)."""
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    n_tiles = tiles_x * tiles_y
    tile_bits = n_tiles.bit_length()
    packed = meta["gaussian_ids"] is not None
    n_cameras, n = depths.shape
    counts, flat, keys, per_gauss = [], [], [], []
    for c, plan in enumerate(plans or [None] * n_cameras):
        if plan is None:
            counts.append(np.zeros(n_tiles, np.int64))
            per_gauss.append(np.zeros(n, np.int64))
            continue
        ranges = plan.ranges.get().astype(np.int64).reshape(n_tiles, 2)
        ids = plan.ids.get()[:plan.n_keys].astype(np.int64)
        count = ranges[:, 1] - ranges[:, 0]
        tile = np.repeat(np.arange(n_tiles), count)
        depth_bits = depths[c].detach().numpy().astype(np.float32).view(np.uint32).astype(np.int64)
        counts.append(count)
        per_gauss.append(np.bincount(ids, minlength=n))
        keys.append((c << (32 + tile_bits)) | (tile << 32) | depth_bits[ids])
        if packed:
            rows = np.full(n, -1, np.int64)
            mine = (meta["camera_ids"] == c).numpy()
            rows[meta["gaussian_ids"].numpy()[mine]] = np.flatnonzero(mine)
            flat.append(rows[ids])
        else:
            flat.append(c * n + ids)
    count = np.concatenate(counts)
    per_gauss = np.stack(per_gauss)
    if packed:
        per_gauss = per_gauss[meta["camera_ids"].numpy(), meta["gaussian_ids"].numpy()]

    def cat(parts: list[np.ndarray], dtype) -> torch.Tensor:
        return torch.from_numpy(np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype))
    offsets = (np.cumsum(count) - count).astype(np.int32).reshape(n_cameras, tiles_y, tiles_x)
    return {"tile_width": tiles_x, "tile_height": tiles_y,
            "tiles_per_gauss": torch.from_numpy(per_gauss.astype(np.int32)), "isect_ids": cat(keys, np.int64),
            "flatten_ids": cat(flat, np.int32), "isect_offsets": torch.from_numpy(offsets)}


def rasterization(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                  colors: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                  near_plane: float = 0.01, far_plane: float = 1e10, radius_clip: float = 0.0, eps2d: float = 0.3,
                  sh_degree: int | None = None, packed: bool = True, tile_size: int = TILE,
                  backgrounds: torch.Tensor | None = None, render_mode: str = "RGB", sparse_grad: bool = False,
                  absgrad: bool = False, rasterize_mode: str = "classic", channel_chunk: int = 32,
                  distributed: bool = False, camera_model: str = "pinhole", segmented: bool = False,
                  covars: torch.Tensor | None = None, with_ut: bool = False, with_eval3d: bool = False,
                  radial_coeffs: torch.Tensor | None = None, tangential_coeffs: torch.Tensor | None = None,
                  thin_prism_coeffs: torch.Tensor | None = None, ftheta_coeffs: object | None = None,
                  viewmats_rs: torch.Tensor | None = None, *, sampler: str = "volume", k: int = 40,
                  extra_signals: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render N 3D Gaussians for C pinhole cameras, as gsplat's ``rasterization`` (gsplat 1.5's
    arguments in its order; qr-cl's own are keyword-only).

    Args (gsplat's names and shapes; float32 CPU tensors):
        means [N,3]; quats [N,4] w,x,y,z (normalized here, need not be unit); scales [N,3] and
        opacities [N] activated.
        colors: [N,D] or [C,N,D] features (D in 1..2048, or 2047 with a depth mode); with
            ``sh_degree``: SH coefficients [N,K,3] or [C,N,K,3].
        viewmats [C,4,4] world-to-camera (OpenCV axes); Ks [C,3,3] px; width, height px.
        near_plane, far_plane: culling by camera z.
        packed: gsplat's default True: the 2-D meta tensors are [nnz, ...] over the (camera,
            Gaussian) pairs that are not culled, with ``camera_ids`` and ``gaussian_ids`` [nnz];
            False: [C, N, ...] (culled Gaussians have radii 0). The images are the same.
        backgrounds: [C,D] or None (black); depth channels get background 0.
        render_mode: "RGB" (the D color channels), "D" (accumulated depth sum_i w_i z_i), "ED"
            (expected depth, D / alpha), "RGB+D", "RGB+ED" (depth as the last channel).
        absgrad: gsplat's AbsGS option: after backward, ``meta["means2d"].absgrad`` (the shape of
            meta["means2d"]) holds per Gaussian the sum over the pixels (the selection's entries)
            of the absolute per-pixel dL/dmean2d, x and y apart (px^-1 units of the loss); it
            accumulates over backward passes as ``.grad`` does. It is summed per pixel before any
            split: a render whose table is split into row parts (too large for one device buffer)
            adds the parts' dL/dw per entry first, then takes the absolute values.
        channel_chunk: accepted for compatibility; it has no effect (the channels are blended
            together).
        sampler, k (qr-cl's own): "volume" (gsplat's alpha blending, the default), "quantile"
            (Q-Render with K = k), "topk" or "stratified" (see :func:`qr_cl.rasterize`).
        extra_signals (qr-cl's own): [N,F] or [C,N,F] per-Gaussian signals (e.g. 512-D features,
            F in 1..2048) blended through the colors' selection (one plan, one selection walk per
            ray, then a blend of their own): returned as ``meta["render_extra_signals"]``
            [C,H,W,F] (background 0), differentiable as the colors are (with absgrad, the
            colors' and the signals' per-pixel terms are added in absolute value apart).
        The other gsplat arguments are accepted only at the values in :data:`UNSUPPORTED`.

    Returns:
        render_colors [C,H,W,X] (X = D, 1 or D+1 by render_mode), render_alphas [C,H,W,1], and
        meta with gsplat's keys:
            radii [C,N,2] (packed: [nnz,2]) int32, x and y half-extents in px of the box each
            Gaussian is binned within (0 = culled); means2d [C,N,2] px, conics [C,N,3] (the inverse
            2D covariance A, B, C), depths [C,N] camera z, opacities [C,N] (packed: [nnz, ...]
            each); batch_ids, camera_ids, gaussian_ids ([nnz] int64, None when not packed);
            tile_width, tile_height, tile_size, width, height, n_cameras, n_batches (1),
            isect_offsets [C,tile_height,tile_width], flatten_ids [n_isects], isect_ids,
            tiles_per_gauss (gsplat's layout: see :func:`_intersections`); plus qr-cl's
            "selections" (the :class:`qr_cl.stages.select.Selection` of each camera).
        means2d, conics, depths and opacities are tensors in the graph (non-leaf, as in gsplat):
        call ``meta["means2d"].retain_grad()`` before backward to read ``.grad`` (in px).

    Gradients flow to means, quats, scales, opacities, colors (and SH coefficients), backgrounds,
    extra_signals and viewmats (rotation and translation, through the projection, the depth
    channel and the SH view directions), through the EWA projection, the 2D conic and alpha, for
    every sampler; the backward is deterministic (bitwise identical run to run). For the K
    samplers the selection is piecewise constant in the geometry and render_alphas carries no
    gradient. Ks get no gradient (Ks that require one raise a ValueError). Each camera renders
    through :func:`qr_cl.render.engine.render_view`, as :func:`qr_cl.rasterize` does: the same
    color stage (sh.cl) and the same splitting of renders larger than the device's largest
    buffer.
    """
    _check_options(dict(radius_clip=radius_clip, eps2d=eps2d, tile_size=tile_size, sparse_grad=sparse_grad,
                        rasterize_mode=rasterize_mode, distributed=distributed, camera_model=camera_model,
                        segmented=segmented, covars=covars, with_ut=with_ut, with_eval3d=with_eval3d,
                        radial_coeffs=radial_coeffs, tangential_coeffs=tangential_coeffs,
                        thin_prism_coeffs=thin_prism_coeffs, ftheta_coeffs=ftheta_coeffs, viewmats_rs=viewmats_rs))
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode={render_mode!r}: supported modes are {RENDER_MODES}")
    k = check_sampler(sampler, k)
    n_cameras = viewmats.shape[0] if viewmats.ndim == 3 else -1
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4) or tuple(Ks.shape) != (n_cameras, 3, 3):
        raise ValueError(f"viewmats must be [C,4,4] and Ks [C,3,3], got {tuple(viewmats.shape)} and {tuple(Ks.shape)}")
    means, quats, scales, opacities = gaussian_tensors(means, quats, scales, opacities)
    if torch.is_grad_enabled() and Ks.requires_grad:
        raise ValueError("gradients w.r.t. Ks (camera intrinsics) are not implemented, as in gsplat; pass Ks "
                         "detached (viewmats may require grad)")
    n = means.shape[0]
    rt = checked_runtime()
    per_colors = _per_camera(colors, n_cameras, 2 if sh_degree is None else 3,
                             "colors" if sh_degree is None else f"colors (SH coefficients, sh_degree={sh_degree})")
    per_extra = [None] * n_cameras if extra_signals is None else _per_camera(extra_signals, n_cameras, 2,
                                                                           "extra_signals")
    if any(e is not None and e.shape[0] != n for e in per_extra):
        raise ValueError(f"extra_signals has shape {tuple(extra_signals.shape)}, expected [{n}, F] or "
                         f"[{n_cameras}, {n}, F]")
    per_bg = [None] * n_cameras if backgrounds is None else _per_camera(backgrounds, n_cameras, 1, "backgrounds")
    per_bg = [_with_depth(bg, render_mode) for bg in per_bg]
    view_t = viewmats.to("cpu", torch.float32)
    views = [View(view_t[c].detach().numpy().copy(), Ks[c].detach().cpu().numpy().astype(np.float32),
                  int(width), int(height), float(near_plane), float(far_plane), sampler, k)
             for c in range(n_cameras)]
    if n:
        plans, means2d, conics, depths = project_view(means, quats, scales, opacities, views, view_t, rt=rt)
    else:
        plans, means2d, conics, depths = (None, means.new_zeros(n_cameras, 0, 2), means.new_zeros(n_cameras, 0, 3),
                                          means.new_zeros(n_cameras, 0))
    meta, splats, depths, sinks = _two_d(plans, means2d, conics, depths, opacities, packed, absgrad and n > 0)
    images, alphas, renders, extras = [], [], [], []
    for c in range(n_cameras):
        features = None
        if render_mode not in ("D", "ED"):
            features = per_colors[c] if sh_degree is None else sh_colors(per_colors[c], means, view_t[c], sh_degree, rt)
        if render_mode != "RGB":
            features = depths[c][:, None] if features is None else torch.cat([features, depths[c][:, None]], 1)
        out = render_view(means, quats, scales, opacities, features, per_bg[c], views[c], viewmat=view_t[c],
                          splats=splats[c] if n else None, absgrad=sinks[c],
                          extra=None if per_extra[c] is None else per_extra[c].to("cpu", torch.float32), rt=rt)
        image, alpha = out.image.reshape(height, width, -1), out.alpha.reshape(height, width, 1)
        if render_mode.endswith("ED"):
            image = torch.cat([image[..., :-1], image[..., -1:] / alpha.clamp_min(1e-10)], -1)
        if out.extra is not None:
            extras.append(out.extra.reshape(height, width, -1))
        images.append(image)
        alphas.append(alpha)
        renders.append(out)
    meta.update(_intersections(plans, depths, meta, int(width), int(height)))
    meta.update({"width": int(width), "height": int(height), "tile_size": TILE, "n_batches": 1,
                 "n_cameras": n_cameras, "selections": [_selections(r) for r in renders]})
    if extras:
        meta["render_extra_signals"] = torch.stack(extras)
    return torch.stack(images), torch.stack(alphas), meta


def _selections(render: Render):
    """A camera's Selection (a list of them when its render was split into sets of rays)."""
    return render.selections[0] if len(render.selections) == 1 else render.selections


def _plan_of_meta(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor, ranges: np.ndarray,
                  ids: np.ndarray, width: int, height: int) -> RasterPlan:
    """A RasterPlan over gsplat's 2-D tensors of one camera: splats of the rows means2d [R,2],
    conics [R,3], opacities [R] (the depth is not needed past the sort), tile ranges [tiles,2]
    [start, end) into ids [M] (rows, depth-sorted per tile)."""
    rt = checked_runtime()
    rows = means2d.shape[0]
    splats = np.zeros((max(rows, 1), SPLAT_FLOATS), np.float32)   # one unused row when there are none
    splats[:rows, SPLAT.mean] = means2d.detach().cpu().numpy()
    splats[:rows, SPLAT.conic] = conics.detach().cpu().numpy()
    splats[:rows, SPLAT.opacity] = opacities.detach().cpu().numpy()
    with np.errstate(divide="ignore", invalid="ignore"):
        splats[:, SPLAT.sigma_max] = np.log(splats[:, SPLAT.opacity] / ALPHA_MIN)   # as project.cl
    return RasterPlan(runtime=rt, width=width, height=height, splats=to_device(rt, splats),
                      radii=device_zeros(rt, (len(splats), 2), np.int32), ranges=to_device(rt, ranges, np.int32),
                      ids=to_device(rt, ids if len(ids) else np.zeros(1), np.int32), n_keys=len(ids))


def _volume_weights(plan: RasterPlan, rays: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """V-Render's weight alpha_i T_i (T over every Gaussian in front, the whole walk) of the entries
    (rays [E] row-major pixel, ids [E] Gaussian) of ``plan``'s image; 0 where V-Render does not
    blend the Gaussian (a selection sampler never picks one it does not)."""
    volume = select(plan, "volume", 1)
    offsets, count = volume.spans()
    ray_of = np.repeat(np.arange(len(count)), count)
    entry = np.repeat(offsets, count) + np.arange(int(count.sum())) - np.repeat(np.cumsum(count) - count, count)
    n = plan.n_gaussians
    keys = ray_of * n + volume.ids.get()[entry]
    order = np.argsort(keys, kind="stable")
    keys, weights = keys[order], volume.weights.get()[entry][order]
    wanted = rays.astype(np.int64) * n + ids
    at = np.searchsorted(keys, wanted)
    found = at < len(keys)
    found[found] = keys[at[found]] == wanted[found]
    out = np.zeros(len(wanted), np.float32)
    out[found] = weights[at[found]]
    return out


@torch.no_grad()
def rasterize_top_contributing_gaussian_ids(means2d: torch.Tensor, conics: torch.Tensor, opacities: torch.Tensor,
                                            isect_offsets: torch.Tensor, flatten_ids: torch.Tensor,
                                            image_width: int, image_height: int, tile_size: int,
                                            num_depth_samples: int, *, sampler: str = "topk"
                                            ) -> tuple[torch.Tensor, torch.Tensor]:
    """gsplat's top-contributor query (its name and argument order; no gradient): per pixel the
    ``num_depth_samples`` = K Gaussians that ``sampler`` selects, in depth order (front to back),
    and their weights, from :func:`rasterization`'s meta.

    Args:
        means2d [C,N,2] px, conics [C,N,3], opacities [C,N] (dense meta) or [nnz,2], [nnz,3],
        [nnz] (packed meta); isect_offsets [C,tile_height,tile_width] and flatten_ids [n_isects]
        (gsplat's tile intersections); image_width, image_height px; tile_size (16 only); K >= 1.
        sampler (qr-cl's own): "topk" (gsplat's choice: the K largest V-Render weights
        alpha_i T_i), "quantile" (Q-Render's K quantile Gaussians) or "stratified".

    Returns:
        ids [C,H,W,K] int32: the Gaussian (0..N-1 with dense meta; the packed row 0..nnz-1 with
        packed meta), -1 in slots past the pixel's picks; weights [C,H,W,K] float32: each pick's
        V-Render weight alpha_i T_i, T over every Gaussian in front of it (gsplat's "radiance
        weight"; for the quantile and stratified picks too, not their normalized blend weights,
        which ``meta["selections"]`` holds), 0 in empty slots.
    """
    if tile_size != TILE:
        raise ValueError(f"tile_size={tile_size}: only {TILE} is supported")
    if sampler == "volume":
        raise ValueError("sampler='volume' picks no K Gaussians: use 'topk', 'quantile' or 'stratified'")
    k = check_sampler(sampler, num_depth_samples)
    n_cameras, tiles_y, tiles_x = isect_offsets.shape
    if (tiles_x, tiles_y) != (-(-image_width // TILE), -(-image_height // TILE)):
        raise ValueError(f"isect_offsets {tuple(isect_offsets.shape)} does not tile a {image_width}x{image_height} "
                         f"image in {TILE} px tiles")
    packed = means2d.ndim == 2
    n_tiles = tiles_x * tiles_y
    flat = flatten_ids.cpu().numpy().astype(np.int64)
    starts = isect_offsets.cpu().numpy().astype(np.int64).reshape(-1)
    ends = np.append(starts[1:], len(flat))
    n_rays = image_width * image_height
    out_ids = np.full((n_cameras, n_rays, k), -1, np.int32)
    out_w = np.zeros((n_cameras, n_rays, k), np.float32)
    for c in range(n_cameras):
        tiles = slice(c * n_tiles, (c + 1) * n_tiles)
        first = starts[tiles][0]
        ids = flat[first:ends[tiles][-1]] - (0 if packed else c * means2d.shape[1])
        ranges = np.stack([starts[tiles], ends[tiles]], 1) - first
        rows = (means2d, conics, opacities) if packed else (means2d[c], conics[c], opacities[c])
        plan = _plan_of_meta(*rows, ranges, ids, image_width, image_height)
        picks = select(plan, sampler, k).host()
        valid = picks["ids"] >= 0
        rays = np.nonzero(valid)[0]
        out_ids[c, :, :valid.shape[1]] = picks["ids"]
        out_w[c, :, :valid.shape[1]][valid] = _volume_weights(plan, rays, picks["ids"][valid])
    shape = (n_cameras, image_height, image_width, k)
    return torch.from_numpy(out_ids.reshape(shape)), torch.from_numpy(out_w.reshape(shape))
