"""Feature rows on the device: rows of ``cstride`` floats, padded from ``channels`` so that the
kernels take them in whole vectors (:func:`channel_layout`); the first ``channels`` floats of a
row are meaningful."""
from __future__ import annotations

import numpy as np

from .constants import MAX_CHANNELS


def check_channels(channels: int) -> None:
    """ValueError unless 1 <= channels <= MAX_CHANNELS."""
    if not 1 <= channels <= MAX_CHANNELS:
        raise ValueError(f"features have {channels} channels; 1..{MAX_CHANNELS} are supported")


#: CPU shapes: the most vectors of a row one work-item blends (512 floats: a whole 512-D row;
#: the kernels accumulate them RV vectors at a time in registers, kernels/rows.h), so that each
#: entry's id, weight and row address are read once per row instead of once per chunk.
CPU_ROW_VECTORS = 32


def channel_layout(channels: int, gpu_shaped: bool = False) -> tuple[int, int, int]:
    """(VW, NV, cstride) for ``channels`` feature channels.

    VW is the vector width of the kernels (16 from 16 channels up, else the next power of two),
    NV the vectors of a row a work-item blends (CPU shapes: the largest divisor of
    the vector count up to CPU_ROW_VECTORS, so one work-item takes up to 512 floats of a row; GPU
    shapes: 1, so a work-item holds 16 accumulators and more work-items share a row), and cstride
    the padded row length in floats (a multiple of VW * NV; the same for both shapes).
    """
    if channels < 1:
        raise ValueError(f"features need at least one channel, got {channels}")
    vw = 16 if channels >= 16 else 1 << (channels - 1).bit_length()
    n_vec = -(-channels // vw)
    nv = 1 if gpu_shaped else max(d for d in range(1, min(n_vec, CPU_ROW_VECTORS) + 1) if n_vec % d == 0)
    return vw, nv, n_vec * vw


def padded_rows(features: np.ndarray, cstride: int) -> np.ndarray:
    """features [N,C] as a C-contiguous float32 [N,cstride] array (zero columns appended)."""
    features = np.asarray(features, np.float32)
    if features.shape[1] == cstride:
        return np.ascontiguousarray(features)
    out = np.zeros((features.shape[0], cstride), np.float32)
    out[:, :features.shape[1]] = features
    return out


def padded_vector(values, channels: int, cstride: int) -> np.ndarray:
    """A float32 [cstride] row holding the first ``channels`` of ``values`` (zeros if None)."""
    out = np.zeros(cstride, np.float32)
    if values is not None:
        out[:channels] = np.asarray(values, np.float32).reshape(-1)[:channels]
    return out
