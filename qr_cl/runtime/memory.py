"""Device memory shared by every stage: feature-row layout, host<->device copies, zero-copy
outputs, and the one exclusive scan.

Features and images live on the device as rows of ``cstride`` floats (see
:func:`channel_layout`); the first ``channels`` floats of a row are meaningful.
"""
from __future__ import annotations

from contextlib import contextmanager
from functools import lru_cache

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.scan import ExclusiveScanKernel

from .constants import MAX_CHANNELS
from .device import Runtime


class BufferLimitError(ValueError):
    """A buffer would exceed the device's largest allocation; the message names both sizes."""


def check_buffer(rt: Runtime, nbytes: int, what: str) -> None:
    """BufferLimitError unless ``nbytes`` fit in one buffer of ``rt``'s device."""
    limit = rt.max_buffer_bytes
    if nbytes > limit:
        raise BufferLimitError(f"{what} needs {nbytes / 2**20:.1f} MiB in one device buffer; "
                               f"{rt.device.name.strip()} allows {limit / 2**20:.1f} MiB "
                               "(CL_DEVICE_MAX_MEM_ALLOC_SIZE)")


def check_channels(channels: int) -> None:
    """ValueError unless 1 <= channels <= MAX_CHANNELS."""
    if not 1 <= channels <= MAX_CHANNELS:
        raise ValueError(f"features have {channels} channels; 1..{MAX_CHANNELS} are supported")


def channel_layout(channels: int) -> tuple[int, int, int]:
    """(VW, NV, cstride) for ``channels`` feature channels.

    VW is the vector width of the kernels (16 from 16 channels up, else the next power of two),
    NV the vectors a work-item accumulates (4, 2 or 1, whichever divides the vector count), and
    cstride the padded row length in floats (a multiple of VW * NV).
    """
    if channels < 1:
        raise ValueError(f"features need at least one channel, got {channels}")
    vw = 16 if channels >= 16 else 1 << (channels - 1).bit_length()
    n_vec = -(-channels // vw)
    nv = 4 if n_vec % 4 == 0 else 2 if n_vec % 2 == 0 else 1
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


def to_device(rt: Runtime, array: np.ndarray, dtype=np.float32) -> cla.Array:
    """A contiguous device copy of a host array."""
    return cla.to_device(rt.queue, np.ascontiguousarray(array, dtype=dtype))


@contextmanager
def host_output(rt: Runtime, array: np.ndarray):
    """A device buffer that the kernels write straight into ``array`` (C-contiguous host memory).

    Zero-copy on CPU devices (USE_HOST_PTR); on leaving the block the buffer is mapped for
    reading, which on discrete GPUs copies the result into ``array``. Avoids allocating and
    copying a second [H*W, C] image. READ_WRITE: kernels may accumulate into what they wrote.
    """
    buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=array)
    yield buf
    mapped, _ = cl.enqueue_map_buffer(rt.queue, buf, cl.map_flags.READ, 0, array.shape, array.dtype)
    mapped.base.release(rt.queue)
    rt.queue.finish()


@lru_cache(maxsize=None)
def _scan_kernel(context: cl.Context) -> ExclusiveScanKernel:
    return ExclusiveScanKernel(context, np.int32, "a+b", "0")


def exclusive_scan(rt: Runtime, values: cla.Array, out: cla.Array | None = None) -> cla.Array:
    """Exclusive int32 prefix sum of ``values`` into ``out`` (in place when None); returns it."""
    out = values if out is None else out
    _scan_kernel(rt.context)(values, out)
    return out


def last_value(array: cla.Array) -> int:
    """The last element of a non-empty device array, as a Python int."""
    host = np.empty(1, array.dtype)
    cl.enqueue_copy(array.queue, host, array.base_data,
                    src_offset=array.offset + array.dtype.itemsize * (array.size - 1))
    return int(host[0])
