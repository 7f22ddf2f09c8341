"""Numpy twin of project.cl (:mod:`qr_cl.stages.project`), in float64: the EWA projection
written to be read."""
from __future__ import annotations

import numpy as np

from ..runtime import ALPHA_MIN, TILE
from ..scene.gaussians import quat_to_rotmat
from .project import tile_grid

#: The largest radius stored in radii (px), as project.cl's RADIUS_MAX: radii are clamped in float
#: before the int conversion (an out-of-range conversion has no defined value).
RADIUS_MAX = 2 ** 30


def project(means, quats, scales, opacities, viewmat, K, width: int, height: int,
            near: float = 0.01, far: float = 1e10) -> dict[str, np.ndarray]:
    """EWA projection (project.cl). Returns means2d [N,2], conics [N,3], depths [N], radii [N]
    (3-sigma, px; 0 = culled, also when the opacity is below ALPHA_MIN), rects [N,4] tile
    rectangle [x0, y0, x1, y1) of the opacity-aware extent, tiles_touched [N], opacities [N]."""
    means, quats, scales = (np.asarray(a, np.float64) for a in (means, quats, scales))
    view, K = np.asarray(viewmat, np.float64), np.asarray(K, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    W = view[:3, :3]
    p = means @ W.T + view[:3, 3]
    x, y, z = p.T
    rs = quat_to_rotmat(quats) * scales[:, None, :]           # R S
    cov3d = W @ (rs @ rs.transpose(0, 2, 1)) @ W.T            # W R S S^T R^T W^T
    with np.errstate(divide="ignore", invalid="ignore"):
        lim_x = (width - cx) / fx + 0.3 * width / (2 * fx), cx / fx + 0.3 * width / (2 * fx)
        lim_y = (height - cy) / fy + 0.3 * height / (2 * fy), cy / fy + 0.3 * height / (2 * fy)
        tx = z * np.clip(x / z, -lim_x[1], lim_x[0])
        ty = z * np.clip(y / z, -lim_y[1], lim_y[0])
        J = np.zeros((len(means), 2, 3))
        J[:, 0, 0], J[:, 0, 2] = fx / z, -fx * tx / z ** 2
        J[:, 1, 1], J[:, 1, 2] = fy / z, -fy * ty / z ** 2
        cov2d = J @ cov3d @ J.transpose(0, 2, 1) + 0.3 * np.eye(2)
        a, b, c = cov2d[:, 0, 0], cov2d[:, 0, 1], cov2d[:, 1, 1]
        det = a * c - b * b
        mid = 0.5 * (a + c)
        radius = np.ceil(3 * np.sqrt(mid + np.sqrt(np.fmax(0.1, mid * mid - det))))
        mean2d = np.stack([fx * x / z + cx, fy * y / z + cy], -1)
        opacity = np.asarray(opacities, np.float64)
        sigma_max = np.log(opacity / ALPHA_MIN)              # blended where sigma <= sigma_max
        ext = np.fmin(radius[:, None], np.ceil(np.sqrt(2 * sigma_max[:, None] * np.stack([a, c], -1))) + 1)
        tiles = np.array(tile_grid(width, height))
        lo = np.clip(np.trunc((mean2d - ext) / TILE), 0, tiles)
        hi = np.clip(np.trunc((mean2d + ext + TILE - 1) / TILE), 0, tiles)
        touched = np.prod(hi - lo, axis=1)
        finite = np.all(np.abs(mean2d) <= np.finfo(np.float32).max, axis=1)   # as float32
        visible = (z >= near) & (z <= far) & (det > 0) & finite & (opacity >= ALPHA_MIN) & (touched > 0)
        conics = np.stack([c / det, -b / det, a / det], -1)
    zero = ~visible
    return {"means2d": np.where(zero[:, None], 0, mean2d), "conics": np.where(zero[:, None], 0, conics),
            "depths": np.where(zero, 0, z),
            "radii": np.where(zero, 0, np.fmin(radius, RADIUS_MAX)).astype(np.int32),
            "rects": np.where(zero[:, None], 0, np.concatenate([lo, hi], 1)).astype(np.int32),
            "tiles_touched": np.where(zero, 0, touched).astype(np.int64),
            "opacities": np.where(zero, 0, np.asarray(opacities, np.float64))}
