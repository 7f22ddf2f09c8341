"""Numpy twin of vrender.cl (:mod:`qr_cl.stages.vrender`), and the whole reference pipeline
project -> bin/sort -> V-Render."""
from __future__ import annotations

import numpy as np

from ..runtime import T_MIN
from .binning_ref import bin_and_sort, tile_pixels
from .blend_ref import part_rows
from .project_ref import project
from .select_ref import alphas


def volume_weights(alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """V-Render weights w_i = T_i alpha'_i [P, n] and final T [P]: blend in order, stop before
    the first Gaussian that would bring T to <= 1e-4."""
    if alpha.shape[1] == 0:
        return alpha.copy(), np.ones(len(alpha), np.float32)
    t_after = np.cumprod(1 - alpha, axis=1, dtype=np.float32)
    t_before = np.concatenate([np.ones_like(alpha[:, :1]), t_after[:, :-1]], 1)
    stops = (alpha > 0) & (t_after <= T_MIN)
    first_stop = np.where(stops.any(1), stops.argmax(1), alpha.shape[1])
    used = np.arange(alpha.shape[1])[None] < first_stop[:, None]
    t_final = np.where(first_stop < alpha.shape[1],
                       t_before[np.arange(len(alpha)), np.minimum(first_stop, alpha.shape[1] - 1)],
                       t_after[:, -1])
    return np.where(used, alpha * t_before, 0).astype(np.float32), t_final.astype(np.float32)


def vrender(proj: dict, ranges: np.ndarray, ids: np.ndarray, features: np.ndarray, width: int,
            height: int, background=None, row0: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full alpha blending (vrender.cl). features [R,C]: the rows [row0, row0 + R) of the table
    (all N, or a row part: other Gaussians blend no feature). Returns image [H,W,C], alpha
    [H,W,1], expected depth [H,W,1]."""
    features = np.asarray(features, np.float32)
    C = features.shape[1]
    padded = np.concatenate([features, np.zeros((1, C), np.float32)])     # the last row: other parts
    image = np.zeros((height, width, C), np.float32)
    alpha_img = np.zeros((height, width, 1), np.float32)
    depth_img = np.zeros((height, width, 1), np.float32)
    bg = np.zeros(C, np.float32) if background is None else np.asarray(background, np.float32)
    for tile, (start, end) in enumerate(ranges):
        pix = tile_pixels(tile, width, height)
        tile_ids = ids[start:end]
        w, t_final = volume_weights(alphas(proj, tile_ids, pix))
        image[pix[:, 1], pix[:, 0]] = w @ padded[part_rows(tile_ids, row0, len(features))] + t_final[:, None] * bg
        alpha_img[pix[:, 1], pix[:, 0], 0] = 1 - t_final
        wsum = 1 - t_final
        dsum = w @ proj["depths"][tile_ids].astype(np.float32)
        depth_img[pix[:, 1], pix[:, 0], 0] = np.where(t_final < 1, dsum / np.where(wsum > 0, wsum, 1), 0)
    return image, alpha_img, depth_img


def render(means, quats, scales, opacities, features, viewmat, K, width: int, height: int,
           near: float = 0.01, far: float = 1e10, background=None):
    """The whole reference pipeline: project -> bin/sort -> V-Render. Returns (image, alpha, depth, proj)."""
    proj = project(means, quats, scales, opacities, viewmat, K, width, height, near, far)
    ranges, ids = bin_and_sort(proj, width, height)
    return (*vrender(proj, ranges, ids, features, width, height, background), proj)
