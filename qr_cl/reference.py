"""Plain numpy references of the kernels: the same math, written to be read, used by the tests.

Geometry (projection) is computed in float64; per-pixel blending in float32 with the kernel's
order of operations (sequential products of 1 - alpha), so differences stay at rounding level.
"""
from __future__ import annotations

import numpy as np

from .scene import SH_C0, quat_to_rotmat

TILE = 16
ALPHA_MIN, ALPHA_MAX, T_MIN = 1.0 / 255.0, 0.99, 1e-4
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def project(means, quats, scales, opacities, viewmat, K, width: int, height: int,
            near: float = 0.01, far: float = 1e10) -> dict[str, np.ndarray]:
    """EWA projection (project.cl). Returns means2d [N,2], conics [N,3], depths [N], radii [N]
    (0 = culled), rects [N,4] tile rectangle [x0, y0, x1, y1), tiles_touched [N], opacities [N]."""
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
        radius = np.ceil(3 * np.sqrt(mid + np.sqrt(np.maximum(0.1, mid * mid - det))))
        mean2d = np.stack([fx * x / z + cx, fy * y / z + cy], -1)
        tiles = np.array([(width + TILE - 1) // TILE, (height + TILE - 1) // TILE])
        lo = np.clip(np.trunc((mean2d - radius[:, None]) / TILE), 0, tiles)
        hi = np.clip(np.trunc((mean2d + radius[:, None] + TILE - 1) / TILE), 0, tiles)
        touched = np.prod(hi - lo, axis=1)
        visible = (z >= near) & (z <= far) & (det > 0) & (touched > 0)
        conics = np.stack([c / det, -b / det, a / det], -1)
    zero = ~visible
    return {"means2d": np.where(zero[:, None], 0, mean2d), "conics": np.where(zero[:, None], 0, conics),
            "depths": np.where(zero, 0, z), "radii": np.where(zero, 0, radius).astype(np.int32),
            "rects": np.where(zero[:, None], 0, np.concatenate([lo, hi], 1)).astype(np.int32),
            "tiles_touched": np.where(zero, 0, touched).astype(np.int64),
            "opacities": np.where(zero, 0, np.asarray(opacities, np.float64))}


def sh_to_rgb(means, sh, campos) -> np.ndarray:
    """RGB [N,3] = max(0, SH(dir) . coefficients + 0.5), dir = normalize(mean - campos) (sh.cl)."""
    sh = np.asarray(sh, np.float64)
    degree = int(round(np.sqrt(sh.shape[1]))) - 1
    d = np.asarray(means, np.float64) - np.asarray(campos, np.float64)
    x, y, z = (d / np.linalg.norm(d, axis=1, keepdims=True)).T[:, :, None]
    basis = [SH_C0 * np.ones_like(x)]
    if degree > 0:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree > 1:
        basis += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * z * z - x * x - y * y),
                  SH_C2[3] * x * z, SH_C2[4] * (x * x - y * y)]
    if degree > 2:
        basis += [SH_C3[0] * y * (3 * x * x - y * y), SH_C3[1] * x * y * z,
                  SH_C3[2] * y * (4 * z * z - x * x - y * y), SH_C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y),
                  SH_C3[4] * x * (4 * z * z - x * x - y * y), SH_C3[5] * z * (x * x - y * y),
                  SH_C3[6] * x * (x * x - 3 * y * y)]
    rgb = sum(bk * sh[:, i] for i, bk in enumerate(basis))
    return np.maximum(rgb + 0.5, 0.0)


def bin_and_sort(proj: dict, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-tile depth-sorted Gaussian ids (binning.cl + sort). Returns (ranges [tiles,2], ids [M])."""
    tiles_x = (width + TILE - 1) // TILE
    n_tiles = tiles_x * ((height + TILE - 1) // TILE)
    tile_ids, gauss_ids = [], []
    for i in np.flatnonzero(proj["radii"] > 0):
        x0, y0, x1, y1 = proj["rects"][i]
        tys, txs = np.mgrid[y0:y1, x0:x1]
        tile_ids.append((tys * tiles_x + txs).ravel())
        gauss_ids.append(np.full(tys.size, i))
    tile_ids = np.concatenate(tile_ids) if tile_ids else np.zeros(0, np.int64)
    gauss_ids = np.concatenate(gauss_ids) if gauss_ids else np.zeros(0, np.int64)
    depth32 = proj["depths"].astype(np.float32)[gauss_ids]   # the kernel sorts float32 depths
    order = np.lexsort((gauss_ids, depth32, tile_ids))
    tile_ids, ids = tile_ids[order], gauss_ids[order]
    starts = np.searchsorted(tile_ids, np.arange(n_tiles), "left")
    ends = np.searchsorted(tile_ids, np.arange(n_tiles), "right")
    return np.stack([starts, ends], 1), ids


def tile_pixels(tile: int, width: int, height: int) -> np.ndarray:
    """Pixel coordinates [P,2] (x, y) of one tile, clipped to the image."""
    tiles_x = (width + TILE - 1) // TILE
    ys, xs = np.mgrid[0:TILE, 0:TILE]
    xs, ys = xs.ravel() + (tile % tiles_x) * TILE, ys.ravel() + (tile // tiles_x) * TILE
    keep = (xs < width) & (ys < height)
    return np.stack([xs[keep], ys[keep]], 1)


def alphas(proj: dict, ids: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """alpha'_i [P, n] of Gaussians ``ids`` (depth order) at pixel centres ``pixels`` [P,2];
    0 where skipped (sigma < 0 or alpha < 1/255), clamped at 0.99."""
    m = proj["means2d"][ids].astype(np.float32)
    con = proj["conics"][ids].astype(np.float32)
    d = m[None] - (pixels.astype(np.float32) + 0.5)[:, None]
    sigma = 0.5 * (con[:, 0] * d[..., 0] ** 2 + con[:, 2] * d[..., 1] ** 2) + con[:, 1] * d[..., 0] * d[..., 1]
    alpha = np.minimum(np.float32(ALPHA_MAX), proj["opacities"][ids].astype(np.float32) * np.exp(-sigma))
    return np.where((sigma >= 0) & (alpha >= np.float32(ALPHA_MIN)), alpha, np.float32(0)).astype(np.float32)


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
            height: int, background=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full alpha blending (vrender.cl). features [N,C]. Returns image [H,W,C], alpha [H,W,1],
    expected depth [H,W,1]."""
    features = np.asarray(features, np.float32)
    C = features.shape[1]
    image = np.zeros((height, width, C), np.float32)
    alpha_img = np.zeros((height, width, 1), np.float32)
    depth_img = np.zeros((height, width, 1), np.float32)
    bg = np.zeros(C, np.float32) if background is None else np.asarray(background, np.float32)
    for tile, (start, end) in enumerate(ranges):
        pix = tile_pixels(tile, width, height)
        tile_ids = ids[start:end]
        w, t_final = volume_weights(alphas(proj, tile_ids, pix))
        image[pix[:, 1], pix[:, 0]] = w @ features[tile_ids] + t_final[:, None] * bg
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


# ---- samplers (select.cl) and blend (blend.cl) ----

def quantile_boundary(k: int, K: int) -> np.float32:
    """The (k+1)-th of the K equal transmittance boundaries, 1 - (k+1)/(K+1), in float32."""
    return np.float32(1) - np.float32(k + 1) / np.float32(K + 1)


def _normalize(w: np.ndarray) -> np.ndarray:
    """w / (1 - T^Q), with 1 - T^Q computed as the float32 sum of w (equal by telescoping, better
    conditioned), summed sequentially as select.cl does."""
    total = np.float32(0)
    for x in w:
        total = total + x
    return (w / total).astype(np.float32) if len(w) else w


def quantile_select(alpha: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Algorithm 1 of the paper on one ray, literally. alpha [n] float32 alpha'_i in depth order
    (0 = skipped). Returns (positions [m] of the quantile Gaussians, their weights [m] normalized by
    1 / (1 - T^Q), T^Q, T where the walk stopped)."""
    one = np.float32(1)
    T, TQ, k = one, one, 0
    pos, w = [], []
    for i in np.flatnonzero(alpha):
        a = np.float32(alpha[i])
        t_test = T * (one - a)
        if t_test < quantile_boundary(k, K):
            pos.append(i)
            w.append(TQ * a)
            TQ = TQ * (one - a)
            k += 1
            while t_test < quantile_boundary(k, K):
                k += 1
        T = t_test
        if t_test < one / np.float32(K + 1):
            break
    weights = _normalize(np.asarray(w, np.float32))
    return np.asarray(pos, np.int64), weights.astype(np.float32), float(TQ), float(T)


def volume_select(alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """V-Render on one ray: (positions [m] of every Gaussian blended, w_i = T_i alpha'_i [m], final T)."""
    one = np.float32(1)
    T = one
    pos, w = [], []
    for i in np.flatnonzero(alpha):
        a = np.float32(alpha[i])
        next_t = T * (one - a)
        if next_t <= np.float32(T_MIN):
            break
        pos.append(i)
        w.append(a * T)
        T = next_t
    return np.asarray(pos, np.int64), np.asarray(w, np.float32), float(T)


def topk_select(alpha: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """top-K on one ray: the K largest V-Render weights (ties: earlier depth first), re-composited in
    depth order among the selected and normalized by 1 / (1 - T). Returns (positions [m] in depth
    order, weights [m], T among the selected before normalization, final T of the V-Render walk)."""
    pos, w, t_final = volume_select(alpha)
    keep = np.sort(pos[np.lexsort((pos, -w))[:K]])
    one = np.float32(1)
    TQ, weights = one, []
    for i in keep:
        a = np.float32(alpha[i])
        weights.append(TQ * a)
        TQ = TQ * (one - a)
    weights = _normalize(np.asarray(weights, np.float32))
    return keep, weights.astype(np.float32), float(TQ), t_final


def select(proj: dict, ranges: np.ndarray, ids: np.ndarray, pixels: np.ndarray, width: int,
           sampler: str, K: int = 0) -> dict[str, np.ndarray]:
    """Selection of rays ``pixels`` [P,2] (x, y) for sampler "volume", "quantile" or "topk".

    proj: means2d, conics, opacities per Gaussian (a RasterPlan's meta() or :func:`project`);
    ranges/ids: per-tile depth-sorted lists. Returns ids [P,L] (-1 padded), weights [P,L]
    (0 padded), count, t_walk, t_sel, t_rem [P], as Selection.host().
    """
    tiles_x = (width + TILE - 1) // TILE
    rows = []
    for x, y in np.asarray(pixels):
        start, end = ranges[(y // TILE) * tiles_x + x // TILE]
        tile_ids = np.asarray(ids[start:end])
        alpha = alphas(proj, tile_ids, np.array([[x, y]]))[0]
        if sampler == "quantile":
            pos, w, t_sel, t_walk = quantile_select(alpha, K)
        elif sampler == "topk":
            pos, w, t_sel, t_walk = topk_select(alpha, K)
        elif sampler == "volume":
            pos, w, t_walk = volume_select(alpha)
            t_sel = t_walk
        else:
            raise ValueError(f"unknown sampler {sampler!r}")
        t_rem = t_walk if sampler == "volume" else float(len(pos) == 0)
        rows.append((tile_ids[pos], w, t_walk, t_sel, t_rem))
    width_l = max([len(r[0]) for r in rows], default=0)
    out = {"ids": np.full((len(rows), width_l), -1, np.int32),
           "weights": np.zeros((len(rows), width_l), np.float32)}
    for p, (g, w, *_) in enumerate(rows):
        out["ids"][p, :len(g)], out["weights"][p, :len(g)] = g, w
    out["count"] = np.array([len(r[0]) for r in rows], np.int32)
    for j, name in enumerate(("t_walk", "t_sel", "t_rem"), start=2):
        out[name] = np.array([r[j] for r in rows], np.float32)
    return out


def blend(ids: np.ndarray, weights: np.ndarray, features: np.ndarray, t_rem: np.ndarray | None = None,
          background=None) -> np.ndarray:
    """image [P,C] = sum_j weights[p,j] features[ids[p,j]] (+ t_rem[p] background), in float64.
    ids [P,L] (-1 = padding), weights [P,L], features [N,C]."""
    f = np.asarray(features, np.float64)
    gathered = f[np.maximum(ids, 0)] * np.where(ids >= 0, weights, 0)[..., None]
    image = gathered.sum(1) if ids.shape[1] else np.zeros((len(ids), f.shape[1]))
    if background is not None:
        image = image + np.asarray(t_rem, np.float64)[:, None] * np.asarray(background, np.float64)[None]
    return image


def quantile_margin(alpha: np.ndarray, K: int) -> float:
    """Smallest relative distance, along Algorithm 1's walk of one ray, between a T_test and a
    transmittance boundary it is compared with (the next quantile boundary or the stop 1/(K+1)).
    Kernel and reference may disagree on a ray only where this is at float rounding level."""
    one = np.float32(1)
    T, k, margin = one, 0, np.inf
    stop = one / np.float32(K + 1)
    for i in np.flatnonzero(alpha):
        t_test = T * (one - np.float32(alpha[i]))
        for b in (quantile_boundary(k, K), stop):
            if b > 0:
                margin = min(margin, abs(float(t_test) - float(b)) / float(b))
        while t_test < quantile_boundary(k, K):
            k += 1
        T = t_test
        if t_test < stop:
            break
    return float(margin)
