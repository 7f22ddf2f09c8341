"""A gsplat-compatible, differentiable rasterizer: :func:`rasterization` takes gsplat's argument
names, shapes and conventions (batched cameras, SH or colours, render modes, backgrounds) and
returns what gsplat returns, with gradients w.r.t. the Gaussians, and Q-Render / top-K as samplers.

A gsplat call ports by changing the import::

    from gsplat import rasterization            ->   from qr_cl import rasterization

gsplat arguments that qr-cl does not implement raise a ValueError naming them (see
:data:`UNSUPPORTED`); none is ignored silently.
"""
from __future__ import annotations

import numpy as np
import torch

from ..runtime import TILE
from ..stages.select import check_sampler
from .autograd import View
from .engine import gaussian_tensors, render_view, sh_colours

RENDER_MODES = ("RGB", "D", "ED", "RGB+D", "RGB+ED")

#: gsplat arguments qr-cl accepts only at one value: name -> (the value, what to do instead).
UNSUPPORTED = {
    "radius_clip": (0.0, "qr-cl culls by near/far planes and opacity only"),
    "eps2d": (0.3, "the 2D low-pass is fixed at 0.3 px (3DGS)"),
    "packed": (False, "meta is returned in gsplat's dense [C, N] layout (packed=False)"),
    "tile_size": (TILE, f"the tile size is fixed at {TILE} px"),
    "sparse_grad": (False, "gradients are dense [N, ...] tensors"),
    "absgrad": (False, "no absolute 2D mean gradients; meta['means2d'] carries no gradient"),
    "rasterize_mode": ("classic", "only 3DGS's classic alpha is implemented, not 'antialiased'"),
    "distributed": (False, "scale out with torch.distributed around the call"),
    "camera_model": ("pinhole", "only pinhole cameras are implemented"),
    "segmented": (False, "no segmented sort"),
    "covars": (None, "pass quats and scales, not covariances"),
    "with_ut": (False, "no unscented transform"),
    "with_eval3d": (False, "no 3D evaluation of the Gaussians"),
}


def _check_options(options: dict) -> None:
    bad = [f"{name}={value!r} ({UNSUPPORTED[name][1]}; only {UNSUPPORTED[name][0]!r} is supported)"
           for name, value in options.items() if value != UNSUPPORTED[name][0]]
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
    colour = background[:0] if render_mode in ("D", "ED") else background
    return torch.cat([colour, background.new_zeros(1)])


def rasterization(means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                  colors: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor, width: int, height: int,
                  near_plane: float = 0.01, far_plane: float = 1e10, sh_degree: int | None = None,
                  backgrounds: torch.Tensor | None = None, render_mode: str = "RGB",
                  channel_chunk: int = 32, sampler: str = "volume", k: int = 40,
                  radius_clip: float = 0.0, eps2d: float = 0.3, packed: bool = False,
                  tile_size: int = TILE, sparse_grad: bool = False, absgrad: bool = False,
                  rasterize_mode: str = "classic", distributed: bool = False, camera_model: str = "pinhole",
                  segmented: bool = False, covars: torch.Tensor | None = None, with_ut: bool = False,
                  with_eval3d: bool = False) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """Render N 3D Gaussians for C pinhole cameras, as gsplat's ``rasterization``.

    Args (gsplat's names and shapes; float32 CPU tensors):
        means [N,3]; quats [N,4] w,x,y,z (normalized here, need not be unit); scales [N,3] and
        opacities [N] activated.
        colors: [N,D] or [C,N,D] features (D in 1..2048, or 2047 with a depth mode); with
            ``sh_degree``: SH coefficients [N,K,3] or [C,N,K,3].
        viewmats [C,4,4] world-to-camera (OpenCV axes); Ks [C,3,3] px; width, height px.
        near_plane, far_plane: culling by camera z.
        backgrounds: [C,D] or None (black); depth channels get background 0.
        render_mode: "RGB" (the D colour channels), "D" (accumulated depth sum_i w_i z_i), "ED"
            (expected depth, D / alpha), "RGB+D", "RGB+ED" (depth as the last channel).
        channel_chunk: accepted for compatibility; it has no effect (the channels are blended
            together).
        sampler, k (qr-cl's own): "volume" (gsplat's alpha blending, the default), "quantile"
            (Q-Render with K = k), "topk" or "stratified" (see :func:`qr_cl.rasterize`).
        The other gsplat arguments are accepted only at the values in :data:`UNSUPPORTED`.

    Returns:
        render_colors [C,H,W,X] (X = D, 1 or D+1 by render_mode), render_alphas [C,H,W,1], and
        meta with gsplat's keys radii [C,N] int32 (one 3-sigma radius per Gaussian, px; gsplat
        >= 1.5 returns [C,N,2]), means2d [C,N,2] px, depths [C,N], conics [C,N,3],
        opacities [C,N], tile_width, tile_height, tile_size, width, height, n_cameras,
        isect_offsets [C,tile_height,tile_width] (the first key of each tile), flatten_ids (a list,
        per camera: depth-sorted Gaussian ids per tile), plus "selections" (the
        :class:`qr_cl.stages.select.Selection` of each camera).

    Gradients flow to means, quats, scales, opacities, colors (and SH coefficients), and
    backgrounds, through the EWA projection, the 2D conic and alpha, for every sampler; the
    backward is deterministic (bitwise identical run to run). For the K samplers the selection is
    piecewise constant in the geometry and render_alphas carries no gradient. The meta entries
    are plain tensors without gradients. Cameras get no gradient: viewmats or Ks that require
    one raise a ValueError. Each camera renders through :func:`qr_cl.render.engine.render_view`,
    as :func:`qr_cl.rasterize` does: the same colour stage (sh.cl) and the same splitting of
    renders larger than the device's largest buffer.
    """
    _check_options(dict(radius_clip=radius_clip, eps2d=eps2d, packed=packed, tile_size=tile_size,
                        sparse_grad=sparse_grad, absgrad=absgrad, rasterize_mode=rasterize_mode,
                        distributed=distributed, camera_model=camera_model, segmented=segmented,
                        covars=covars, with_ut=with_ut, with_eval3d=with_eval3d))
    if render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode={render_mode!r}: supported modes are {RENDER_MODES}")
    k = check_sampler(sampler, k)
    n_cameras = viewmats.shape[0] if viewmats.ndim == 3 else -1
    if viewmats.ndim != 3 or viewmats.shape[1:] != (4, 4) or tuple(Ks.shape) != (n_cameras, 3, 3):
        raise ValueError(f"viewmats must be [C,4,4] and Ks [C,3,3], got {tuple(viewmats.shape)} and {tuple(Ks.shape)}")
    means, quats, scales, opacities = gaussian_tensors(means, quats, scales, opacities)
    if torch.is_grad_enabled() and (viewmats.requires_grad or Ks.requires_grad):
        raise ValueError("gradients w.r.t. viewmats and Ks (camera optimisation) are not implemented; "
                         "pass them detached")
    per_colors = _per_camera(colors, n_cameras, 2 if sh_degree is None else 3,
                             "colors" if sh_degree is None else f"colors (SH coefficients, sh_degree={sh_degree})")
    per_bg = [None] * n_cameras if backgrounds is None else _per_camera(backgrounds, n_cameras, 1, "backgrounds")
    per_bg = [_with_depth(bg, render_mode) for bg in per_bg]
    images, alphas, renders = [], [], []
    for c in range(n_cameras):
        view = View(viewmats[c].detach().cpu().numpy().astype(np.float32),
                    Ks[c].detach().cpu().numpy().astype(np.float32),
                    int(width), int(height), float(near_plane), float(far_plane), sampler, k)
        features = None
        if render_mode not in ("D", "ED"):
            features = per_colors[c] if sh_degree is None else sh_colours(per_colors[c], means, view.viewmat, sh_degree)
        if render_mode != "RGB":
            depth = (means @ viewmats[c, 2, :3].detach() + viewmats[c, 2, 3].detach())[:, None]
            features = depth if features is None else torch.cat([features, depth], 1)
        out = render_view(means, quats, scales, opacities, features, per_bg[c], view)
        image, alpha = out.image.reshape(height, width, -1), out.alpha.reshape(height, width, 1)
        if render_mode.endswith("ED"):
            image = torch.cat([image[..., :-1], image[..., -1:] / alpha.clamp_min(1e-10)], -1)
        images.append(image)
        alphas.append(alpha)
        renders.append(out)
    return torch.stack(images), torch.stack(alphas), _meta(renders, means.shape[0], width, height)


def _meta(renders: list, n: int, width: int, height: int) -> dict:
    """gsplat's meta keys, stacked over cameras, from each camera's :class:`~qr_cl.render.engine.Render`
    (a render of no Gaussians has the keys, empty)."""
    tiles_x, tiles_y = -(-width // TILE), -(-height // TILE)
    plans = [r.plan.meta() if r.plan is not None else None for r in renders]

    def stack(key: str, shape: tuple, dtype) -> torch.Tensor:
        return torch.from_numpy(np.stack([p[key] if p is not None else np.zeros(shape, dtype) for p in plans]))
    ranges = [p["tile_ranges"][:, 0].reshape(tiles_y, tiles_x) if p is not None
              else np.zeros((tiles_y, tiles_x), np.int32) for p in plans]
    return {"radii": stack("radii", (n,), np.int32), "means2d": stack("means2d", (n, 2), np.float32),
            "depths": stack("depths", (n,), np.float32), "conics": stack("conics", (n, 3), np.float32),
            "opacities": stack("opacities", (n,), np.float32), "isect_offsets": torch.from_numpy(np.stack(ranges)),
            "flatten_ids": [torch.from_numpy(p["flatten_ids"].copy()) if p is not None
                            else torch.zeros(0, dtype=torch.int32) for p in plans],
            "tile_width": tiles_x, "tile_height": tiles_y, "tile_size": TILE, "width": width,
            "height": height, "n_cameras": len(renders),
            "selections": [r.selections[0] if len(r.selections) == 1 else r.selections for r in renders]}
