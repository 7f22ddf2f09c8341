"""Twin of project.cl (:mod:`qr_cl.stages.project`), in float64: the EWA projection written to be
read. :func:`ewa` is differentiable torch (the reference of ``project_backward``);
:func:`project` adds culling and tile rectangles in numpy."""
from __future__ import annotations

import numpy as np
import torch

from ..runtime import ALPHA_MIN, TILE
from ..runtime.constants import (SPAN_COND_MAX, SPAN_DET_MIN, SPAN_MARGIN_PX, SPAN_MARGIN_REL, SPAN_ROUNDING,
                                 SPAN_SLACK)
from ..scene.gaussians import quat_to_rotmat
from .project import tile_grid

#: The largest radius stored in radii (px), as project.cl's RADIUS_MAX: radii are clamped in float
#: before the int conversion (an out-of-range conversion has no defined value).
RADIUS_MAX = 2 ** 30


def _tensor(x) -> torch.Tensor:
    """x as a float64 tensor (tensors keep their autograd graph)."""
    return x.double() if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x, np.float64))


def ewa(means, quats, scales, viewmat, K, width: int, height: int) -> dict[str, torch.Tensor]:
    """The EWA projection of 3DGS in float64 torch, differentiable w.r.t. every input: means [N,3],
    quats [N,4] (used as given: the unit-quaternion rotation formula), scales [N,3], viewmat [4,4]
    world-to-camera, K [3,3] px. Returns p [N,3] (camera frame), means2d [N,2] px, cov2d [N,3]
    (a, b, c of the 2D covariance, 0.3 px low-pass included) and conics [N,3] (its inverse A, B, C)."""
    means, quats, scales, view, K = (_tensor(a) for a in (means, quats, scales, viewmat, K))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    W = view[:3, :3]
    p = means @ W.T + view[:3, 3]
    x, y, z = p.T
    rs = quat_to_rotmat(quats) * scales[:, None, :]           # R S
    cov3d = W @ (rs @ rs.transpose(1, 2)) @ W.T                # W R S S^T R^T W^T
    lim_x = (width - cx) / fx + 0.3 * width / (2 * fx), cx / fx + 0.3 * width / (2 * fx)
    lim_y = (height - cy) / fy + 0.3 * height / (2 * fy), cy / fy + 0.3 * height / (2 * fy)
    tx = z * torch.clamp(x / z, -lim_x[1], lim_x[0])
    ty = z * torch.clamp(y / z, -lim_y[1], lim_y[0])
    zero = torch.zeros_like(z)
    J = torch.stack([torch.stack([fx / z, zero, -fx * tx / z ** 2], -1),
                     torch.stack([zero, fy / z, -fy * ty / z ** 2], -1)], 1)
    cov2d = J @ cov3d @ J.transpose(1, 2) + 0.3 * torch.eye(2, dtype=J.dtype)
    a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
    det = a * c - b * b
    return {"p": p, "means2d": torch.stack([fx * x / z + cx, fy * y / z + cy], -1),
            "cov2d": torch.stack([a, b, c], -1), "conics": torch.stack([c / det, -b / det, a / det], -1)}


def project(means, quats, scales, opacities, viewmat, K, width: int, height: int,
            near: float = 0.01, far: float = 1e10) -> dict[str, np.ndarray]:
    """EWA projection (project.cl). Returns means2d [N,2], conics [N,3], depths [N], radii [N,2]
    (x, y px: the half-sides of the opacity-aware box, at most the 3-sigma radius; 0 = culled, also
    when the opacity is below ALPHA_MIN), rects [N,4] tile
    rectangle [x0, y0, x1, y1) of the opacity-aware extent, tiles_touched [N] (the tiles of its
    rows' :func:`tile_spans`), opacities [N]."""
    with np.errstate(divide="ignore", invalid="ignore"), torch.no_grad():
        e = {k: v.numpy() for k, v in ewa(means, quats, scales, viewmat, K, width, height).items()}
        z = e["p"][:, 2]
        a, b, c = e["cov2d"].T
        det = a * c - b * b
        mid = 0.5 * (a + c)
        radius = np.ceil(3 * np.sqrt(mid + np.sqrt(np.fmax(0.1, mid * mid - det))))
        mean2d = e["means2d"]
        opacity = np.asarray(opacities, np.float64)
        sigma_max = np.log(opacity / ALPHA_MIN)              # blended where sigma <= sigma_max
        ext = np.fmin(radius[:, None], np.ceil(np.sqrt(2 * sigma_max[:, None] * np.stack([a, c], -1))) + 1)
        tiles = np.array(tile_grid(width, height))
        lo = np.clip(np.trunc((mean2d - ext) / TILE), 0, tiles)
        hi = np.clip(np.trunc((mean2d + ext + TILE - 1) / TILE), 0, tiles)
        rects = np.concatenate([lo, hi], 1).astype(np.int64)
        touched = np.zeros(len(z), np.int64)
        for i in np.flatnonzero(np.prod(hi - lo, axis=1) > 0):
            spans = tile_spans(mean2d[i], e["conics"][i], opacity[i], rects[i], int(tiles[0]))
            touched[i] = np.maximum(spans[:, 2] - spans[:, 1], 0).sum()
        finite = np.all(np.abs(mean2d) <= np.finfo(np.float32).max, axis=1)   # as float32
        visible = (z >= near) & (z <= far) & (det > 0) & finite & (opacity >= ALPHA_MIN) & (touched > 0)
    zero = ~visible
    return {"means2d": np.where(zero[:, None], 0, mean2d), "conics": np.where(zero[:, None], 0, e["conics"]),
            "depths": np.where(zero, 0, z),
            "radii": np.where(zero[:, None], 0, np.fmin(ext, RADIUS_MAX)).astype(np.int32),
            "rects": np.where(zero[:, None], 0, rects).astype(np.int32),
            "tiles_touched": np.where(zero, 0, touched).astype(np.int64),
            "opacities": np.where(zero, 0, opacity)}


def tile_spans(mean2d, conic, opacity: float, rect, tiles_x: int) -> np.ndarray:
    """The tiles of each tile row of ``rect`` [x0, y0, x1, y1) that the blend ellipse of a splat
    reaches (tile_spans in kernels/spans.h, the same widening against rounding): mean2d [2] px,
    conic [3] (a, b, c), the ellipse sigma <= ln(opacity / ALPHA_MIN). Returns [rows, 3] int64
    (ty, x0, x1): tiles [x0, x1) of row ty, empty when x0 >= x1."""
    x0, y0, x1, y1 = (int(v) for v in rect)
    ty = np.arange(y0, y1)
    whole = np.stack([ty, np.full_like(ty, x0), np.full_like(ty, x1)], 1)
    (mx, my), (a, b, c) = np.asarray(mean2d, np.float64), np.asarray(conic, np.float64)
    with np.errstate(all="ignore"):
        det = a * c - b * b
        cond = a * c / det
        if not (det > SPAN_DET_MIN and cond <= SPAN_COND_MAX) or (x1 - x0) * (y1 - y0) == 1:
            return whole                                            # needles and single tiles
        big_l = (np.log(opacity / ALPHA_MIN) + SPAN_SLACK) * (1 + SPAN_ROUNDING * np.finfo(np.float32).eps * cond)
        e_x, e_y = np.sqrt(2 * big_l * c / det), np.sqrt(2 * big_l * a / det)
        lo, hi = np.fmax(ty * TILE - my, -e_y), np.fmin((ty + 1) * TILE - my, e_y)
        band = lo <= hi                                             # rows the ellipse reaches
        dr = np.clip(-b * e_x / c, lo, np.fmax(lo, hi))             # where the chord's ends are extreme
        dl = np.clip(b * e_x / c, lo, np.fmax(lo, hi))
        right = (-b * dr + np.sqrt(np.fmax(0, 2 * big_l * a - det * dr * dr))) / a
        left = (-b * dl - np.sqrt(np.fmax(0, 2 * big_l * a - det * dl * dl))) / a
        margin = SPAN_MARGIN_PX + SPAN_MARGIN_REL * e_x

        def tile_index(v):
            return np.fmin(np.fmax(v / TILE, 0), tiles_x).astype(np.int64)
        tx0 = np.maximum(x0, tile_index(mx + left - margin))
        tx1 = np.minimum(x1, tile_index(mx + right + margin) + 1)
    return np.stack([ty, np.where(band, tx0, 0), np.where(band, tx1, 0)], 1)
