"""Numpy twins of select.cl (:mod:`qr_cl.stages.select`): the samplers ray by ray, written to be read.

Per-pixel math in float32 with the kernels' order of operations (sequential products of
1 - alpha), so differences stay at rounding level.
"""
from __future__ import annotations

import math

import numpy as np

from ..runtime import ALPHA_MAX, ALPHA_MIN, T_MIN, TILE
from .project import tile_grid


def alphas(proj: dict, ids: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """alpha'_i [P, n] of Gaussians ``ids`` (depth order) at pixel centres ``pixels`` [P,2];
    0 where skipped (sigma < 0 or alpha < 1/255), clamped at 0.99."""
    m = proj["means2d"][ids].astype(np.float32)
    con = proj["conics"][ids].astype(np.float32)
    d = m[None] - (pixels.astype(np.float32) + 0.5)[:, None]
    sigma = 0.5 * (con[:, 0] * d[..., 0] ** 2 + con[:, 2] * d[..., 1] ** 2) + con[:, 1] * d[..., 0] * d[..., 1]
    alpha = np.minimum(np.float32(ALPHA_MAX), proj["opacities"][ids].astype(np.float32) * np.exp(-sigma))
    return np.where((sigma >= 0) & (alpha >= np.float32(ALPHA_MIN)), alpha, np.float32(0)).astype(np.float32)


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


def normal_quantile(p: float) -> float:
    """Inverse standard normal CDF by Acklam's rational approximation, clamped to [-8, 8]
    (select.cl's normal_quantile, in float64)."""
    if p <= 0:
        return -8.0
    if p >= 1:
        return 8.0
    lo = 0.02425
    if p < lo or p > 1 - lo:
        q = math.sqrt(-2 * math.log(p if p < lo else 1 - p))
        x = ((((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e+00) * q
                - 2.549671010243101e+00) * q + 4.374664141464968e+00) * q + 2.938163982698783e+00)
             / ((((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e+00) * q
                 + 3.754408661907416e+00) * q + 1))
        x = x if p < lo else -x
    else:
        q = p - 0.5
        r = q * q
        x = ((((((-3.969683028665376e+01 * r + 2.209460984245205e+02) * r - 2.759285104469687e+02) * r
                + 1.383577518672690e+02) * r - 3.066479806614716e+01) * r + 2.506628277459239e+00) * q
             / (((((-5.447609879822406e+01 * r + 1.615858368580409e+02) * r - 1.556989798598866e+02) * r
                  + 6.680131188771972e+01) * r - 1.328068155288572e+01) * r + 1))
    return min(max(x, -8.0), 8.0)


def stratified_boundary(k: int, K: int, mu: float, sigma: float, t_end: float) -> np.float32:
    """Stratified-K's (k+1)-th boundary: the quantile (k+1)/(K+1), counted from T = 1 down, of
    N(mu, sigma^2) cut to [t_end, 1] (uniform in [t_end, 1] when sigma is 0); -1 for k >= K."""
    if k >= K:
        return np.float32(-1)
    f = (k + 1) / (K + 1)
    if not sigma > 0:
        return np.float32(1 - f * (1 - t_end))
    cdf = lambda x: 0.5 * (1 + math.erf(x / math.sqrt(2)))
    p_hi, p_lo = cdf((1 - mu) / sigma), cdf((t_end - mu) / sigma)
    return np.float32(mu + sigma * normal_quantile(p_hi - f * (p_hi - p_lo)))


def stratified_stats(alpha: np.ndarray) -> tuple[float, float, float]:
    """(mean, standard deviation, final value) of the transmittance after each Gaussian of the
    V-Render walk of one ray (1, 0, 1 when it blends nothing)."""
    pos, w, t_final = volume_select(alpha)
    if not len(pos):
        return 1.0, 0.0, 1.0
    t = np.cumprod(1 - alpha[pos].astype(np.float64))
    return float(t.mean()), float(t.std()), float(t_final)


def stratified_select(alpha: np.ndarray, K: int) -> tuple[np.ndarray, np.ndarray, float, float]:
    """Stratified-K (App. E) on one ray: the V-Render walk's transmittance statistics place the
    K boundaries (:func:`stratified_boundary`), then Algorithm 1 walks the same Gaussians with
    them. Returns (positions [m], weights [m] normalized as Q-Render, T^Q, final T)."""
    mu, sigma, t_end = stratified_stats(alpha)
    pos, _, t_final = volume_select(alpha)
    one = np.float32(1)
    T, TQ, k = one, one, 0
    picked, w = [], []
    for i in pos:
        a = np.float32(alpha[i])
        t_test = T * (one - a)
        if t_test < stratified_boundary(k, K, mu, sigma, t_end):
            picked.append(i)
            w.append(TQ * a)
            TQ = TQ * (one - a)
            k += 1
            while t_test < stratified_boundary(k, K, mu, sigma, t_end):
                k += 1
        T = t_test
    return np.asarray(picked, np.int64), _normalize(np.asarray(w, np.float32)), float(TQ), t_final


def stratified_margin(alpha: np.ndarray, K: int) -> float:
    """Smallest relative distance between a T_test of the walk and the boundary it is compared
    with (rays where kernel and twin may differ: float32 statistics vs float64, erf)."""
    mu, sigma, t_end = stratified_stats(alpha)
    pos, _, _ = volume_select(alpha)
    one, T, k, margin = np.float32(1), np.float32(1), 0, np.inf
    for i in pos:
        t_test = T * (one - np.float32(alpha[i]))
        b = stratified_boundary(k, K, mu, sigma, t_end)
        if b > 0:
            margin = min(margin, abs(float(t_test) - float(b)) / float(b))
        while t_test < stratified_boundary(k, K, mu, sigma, t_end):
            k += 1
        T = t_test
    return float(margin)


def select(proj: dict, ranges: np.ndarray, ids: np.ndarray, pixels: np.ndarray, width: int,
           sampler: str, K: int = 0) -> dict[str, np.ndarray]:
    """Selection of rays ``pixels`` [P,2] (x, y) for sampler "volume", "quantile", "topk" or
    "stratified".

    proj: means2d, conics, opacities per Gaussian (a RasterPlan's meta() or
    :func:`qr_cl.stages.project_ref.project`); ranges/ids: per-tile depth-sorted lists. Returns
    ids [P,L] (-1 padded), weights [P,L] (0 padded), count, t_walk, t_sel, t_rem [P], as
    Selection.host().
    """
    tiles_x = tile_grid(width, 1)[0]
    rows = []
    for x, y in np.asarray(pixels):
        start, end = ranges[(y // TILE) * tiles_x + x // TILE]
        tile_ids = np.asarray(ids[start:end])
        alpha = alphas(proj, tile_ids, np.array([[x, y]]))[0]
        if sampler == "quantile":
            pos, w, t_sel, t_walk = quantile_select(alpha, K)
        elif sampler == "topk":
            pos, w, t_sel, t_walk = topk_select(alpha, K)
        elif sampler == "stratified":
            pos, w, t_sel, t_walk = stratified_select(alpha, K)
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
