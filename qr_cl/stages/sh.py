"""Spherical-harmonic color stage (sh.cl): SH coefficients + camera position -> RGB per Gaussian,
and its backward to the coefficients and the means. Twin: :mod:`qr_cl.stages.sh_ref`."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ..runtime import Runtime, device_zeros, to_device


def sh_degree_of(sh: np.ndarray) -> int:
    """The degree d of SH coefficients [N,(d+1)^2,3], d <= 3; ValueError otherwise."""
    degree = int(round(np.sqrt(sh.shape[1]))) - 1 if sh.ndim == 3 else -1
    if sh.ndim != 3 or (degree + 1) ** 2 != sh.shape[1] or degree > 3 or sh.shape[2] != 3:
        raise ValueError(f"SH coefficients must be [N, (d+1)^2, 3] with d <= 3, got {sh.shape}")
    return degree


def sh_colors(rt: Runtime, means: cla.Array, sh: np.ndarray, campos: np.ndarray) -> cla.Array:
    """View-dependent RGB [N,4] (4th channel 0) on the device from SH coefficients
    sh [N,(d+1)^2,3] (d <= 3), Gaussian centres ``means`` [N,3] and the camera centre campos [3]."""
    n = sh.shape[0]
    degree = sh_degree_of(sh)
    colors = device_zeros(rt, (max(n, 1), 4), np.float32)
    if n:
        rt.launch("sh_to_rgb", n, defines={"DEGREE": degree}, n=n, means=means,
                  sh=to_device(rt, sh), campos=campos, colors=colors)
    return colors[:n]


def sh_backward(rt: Runtime, means: cla.Array, sh: np.ndarray, campos: np.ndarray, colors: cla.Array,
                d_colors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d_sh [N,(d+1)^2,3], d_means [N,3]) float32 from the gradient d_colors [N,3] of
    :func:`sh_colors`'s RGB (its output ``colors`` [N,4] tells where the clamp at 0 was active).
    The camera centre gets no gradient."""
    n = sh.shape[0]
    degree = sh_degree_of(sh)
    d_sh, d_means = np.zeros(sh.shape, np.float32), np.zeros((n, 3), np.float32)
    if n:
        d_rgba = np.zeros((n, 4), np.float32)
        d_rgba[:, :3] = d_colors
        out_sh, out_means = device_zeros(rt, d_sh.shape), device_zeros(rt, d_means.shape)
        rt.launch("sh_backward", n, defines={"DEGREE": degree}, n=n, means=means, sh=to_device(rt, sh),
                  campos=campos, colors=colors, d_colors=to_device(rt, d_rgba), d_sh=out_sh, d_means=out_means)
        out_sh.get(ary=d_sh)
        out_means.get(ary=d_means)
    return d_sh, d_means
