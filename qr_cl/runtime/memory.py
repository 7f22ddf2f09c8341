"""Device memory shared by every stage: pooled device arrays, zero-copy host<->device sharing,
tables split into row parts that fit a device buffer, and the one exclusive scan.

Allocation-free calls. Every array a stage allocates per call comes from pools, so a warm call
allocates (and page-faults) nothing:

* device arrays: :func:`device_empty`, :func:`device_zeros`, :func:`to_device` (and anything
  pyopencl derives from their arrays: ``cla.empty_like``, slices, scans, sums use the array's
  allocator) come from ``rt.pool``, a per-Runtime ``pyopencl.tools.MemoryPool``. A buffer goes
  back to the pool when its array is garbage collected; the in-order queue orders its next use
  after every command enqueued on the old one. :func:`trim_device_pool` bounds what it holds.
* host memory the kernels read or write: :func:`shared_array` (any C-contiguous array; ``"r"``
  read-only, ``"w"`` written, ``"rw"``) and :func:`device_rows` (feature rows, padded to cstride
  only when they have to be; a table too large for one buffer in :func:`row_parts`, each
  part's rows by :func:`table_parts`). On a device that shares host memory
  (``rt.host_unified``: CPU devices) they wrap the host array in a USE_HOST_PTR buffer (no
  copy); elsewhere they copy through a pooled device array.
* large host outputs: ``host_empty`` (:mod:`qr_cl.runtime.host_memory`).

Typical stage code::

    counts = device_empty(rt, n, np.int32)             # instead of cla.empty(rt.queue, n, np.int32)
    ranges = device_zeros(rt, (tiles, 2), np.int32)     # instead of cla.zeros(...)
    pix = to_device(rt, pixels, np.int32)               # instead of cla.to_device(rt.queue, ...)
    image = host_empty((h, w, cstride))                 # instead of np.empty(...) for big outputs
    with shared_array(rt, image, "w") as image_dev:     # a cla.Array over image's memory
        rt.launch("kernel", size, image=image_dev, ...)
    # the kernels' writes are in ``image`` here (queue finished)
"""
from __future__ import annotations

import math
import os
import warnings
from contextlib import contextmanager
from functools import lru_cache
from typing import Iterator

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.scan import ExclusiveScanKernel

from .constants import STREAM_MIN_BYTES
from .context import Runtime
from .host_memory import check_host_memory, host_empty


class BufferLimitError(ValueError):
    """A buffer would exceed the device's largest allocation; the message names both sizes."""


def check_buffer(rt: Runtime, nbytes: int, what: str) -> None:
    """BufferLimitError unless ``nbytes`` fit in one buffer of ``rt``'s device."""
    limit = rt.max_buffer_bytes
    if nbytes > limit:
        raise BufferLimitError(f"{what} needs {nbytes / 2**20:.1f} MiB in one device buffer; "
                               f"{rt.device.name.strip()} allows {limit / 2**20:.1f} MiB "
                               "(CL_DEVICE_MAX_MEM_ALLOC_SIZE)")


def streamed(nbytes: int) -> int:
    """The ``stream`` argument of the kernels that write an output of ``nbytes`` bytes: 1 (write it
    with non-temporal stores, VSTREAM in kernels/rows.h) from STREAM_MIN_BYTES, else 0."""
    return int(nbytes >= STREAM_MIN_BYTES)


def _checked(rt: Runtime, shape, dtype) -> None:
    """BufferLimitError (naming the array's shape and bytes) unless it fits in one buffer of rt;
    HostMemoryError where the device's memory is the host's and too little of it is available."""
    shape = (int(shape),) if np.isscalar(shape) else tuple(int(s) for s in shape)
    nbytes, what = math.prod(shape) * np.dtype(dtype).itemsize, f"a device array of {shape} {np.dtype(dtype)}"
    check_buffer(rt, nbytes, what)
    if rt.host_unified:
        check_host_memory(nbytes, what)


def device_empty(rt: Runtime, shape, dtype=np.float32) -> cla.Array:
    """An uninitialised device array from ``rt``'s memory pool (reused from earlier calls);
    BufferLimitError if it exceeds the device's largest buffer."""
    _checked(rt, shape, dtype)
    return cla.empty(rt.queue, shape, dtype, allocator=rt.pool)


def device_zeros(rt: Runtime, shape, dtype=np.float32) -> cla.Array:
    """A zero-filled device array from ``rt``'s memory pool (BufferLimitError as device_empty)."""
    _checked(rt, shape, dtype)
    return cla.zeros(rt.queue, shape, dtype, allocator=rt.pool)


def to_device(rt: Runtime, array, dtype=np.float32) -> cla.Array:
    """A device copy of a host array (converted to ``dtype``) in a buffer from ``rt``'s pool
    (BufferLimitError as device_empty)."""
    array = np.ascontiguousarray(array, dtype=dtype)
    _checked(rt, array.shape, dtype)
    return cla.to_device(rt.queue, array, allocator=rt.pool)


#: Held (free) bytes above which :func:`trim_device_pool` empties the device pool by default.
DEVICE_POOL_HELD_BYTES = int(os.environ.get("QR_CL_DEVICE_POOL_MB", 1024)) << 20


def trim_device_pool(rt: Runtime, max_held_bytes: int | None = None) -> int:
    """Free the buffers ``rt.pool`` holds for reuse when they exceed ``max_held_bytes``
    (default ``$QR_CL_DEVICE_POOL_MB`` MiB, 1024): the pool keeps a buffer per size bin it has
    seen, so renders of varying sizes would otherwise keep their peak. Returns the bytes the pool
    owns afterwards (in use or held). The renderers call it at the end of each call."""
    pool = rt.pool
    limit = DEVICE_POOL_HELD_BYTES if max_held_bytes is None else max_held_bytes
    if pool.held_blocks and pool.managed_bytes - pool.active_bytes > limit:   # held, ~ (bins round up)
        pool.free_held()
    return pool.managed_bytes


# ----------------------------------------------------------------------------------------------
# host memory the kernels use directly
# ----------------------------------------------------------------------------------------------

_ACCESS = {"r": cl.mem_flags.READ_ONLY, "w": cl.mem_flags.READ_WRITE, "rw": cl.mem_flags.READ_WRITE}


@contextmanager
def shared_array(rt: Runtime, host: np.ndarray, access: str = "rw") -> Iterator[cla.Array]:
    """``host`` (a C-contiguous numpy array) as a device array of its shape and dtype, for the
    block; ``access`` says what the kernels do with it: ``"r"`` read, ``"w"`` write (what they
    read before writing is undefined), ``"rw"`` both.

    On a device sharing host memory (``rt.host_unified``) the device array *is* ``host``'s memory
    (a USE_HOST_PTR buffer, nothing copied); on leaving the block a written buffer is mapped for
    reading, the OpenCL way of making the kernels' writes visible to the host (free there).
    Elsewhere it is a pooled device array, filled from ``host`` on entry (``"r"``, ``"rw"``) and
    copied back into ``host`` on leaving (``"w"``, ``"rw"``). Either way the queue is finished on
    leaving (also on an exception), so ``host`` may be read or freed afterwards.
    """
    if access not in _ACCESS:
        raise ValueError(f"access must be 'r', 'w' or 'rw', got {access!r}")
    if not isinstance(host, np.ndarray) or not host.flags.c_contiguous:
        raise ValueError("shared_array needs a C-contiguous numpy array")
    if host.nbytes == 0:                   # no buffer of zero bytes: an empty device array
        yield cla.empty(rt.queue, host.shape, host.dtype)
        return
    check_buffer(rt, host.nbytes, f"a shared host array of {host.shape} {host.dtype}")
    try:
        if rt.host_unified:
            buf = cl.Buffer(rt.context, _ACCESS[access] | cl.mem_flags.USE_HOST_PTR, hostbuf=host)
            yield cla.Array(rt.queue, host.shape, host.dtype, data=buf)
            if "w" in access:
                mapped, _ = cl.enqueue_map_buffer(rt.queue, buf, cl.map_flags.READ, 0, host.shape, host.dtype)
                mapped.base.release(rt.queue)
        else:
            dev = device_empty(rt, host.shape, host.dtype)
            if "r" in access:
                dev.set(host)
            yield dev
            if "w" in access:
                dev.get(ary=host)
    finally:
        rt.queue.finish()


@contextmanager
def device_rows(rt: Runtime, rows: np.ndarray, cstride: int) -> Iterator[cla.Array]:
    """Rows [R, C] (C <= cstride; a numpy array, e.g. ``tensor.detach().numpy()``) as read-only
    [R, cstride] device rows for the block, float16 for float16 rows (a half feature table, see
    ``HALF_ROWS`` in kernels/rows.h), float32 for any other dtype; copied only when they have to be.

    C-contiguous rows of that dtype with C == cstride are used in place (zero-copy on devices
    sharing host memory, at any address on PoCL; one copy into a pooled device array elsewhere),
    and so is a row range ``table[r0:r1]`` of such a table (a row part); other rows are first
    converted and padded with zero columns into a pooled host array (:func:`host_empty`). The
    kernels must not write to them.
    """
    rows = np.asarray(rows)
    if rows.ndim != 2 or rows.shape[1] > cstride:
        raise ValueError(f"rows must be [R, C] with C <= {cstride}, got {rows.shape}")
    dtype = np.dtype(np.float16 if rows.dtype == np.float16 else np.float32)
    check_buffer(rt, dtype.itemsize * rows.shape[0] * cstride, f"{rows.shape[0]} rows x {cstride} {dtype} channels")
    if rows.dtype != dtype or rows.shape[1] != cstride or not rows.flags.c_contiguous:
        padded = host_empty((rows.shape[0], cstride), dtype)
        padded[:, :rows.shape[1]] = rows
        padded[:, rows.shape[1]:] = 0
        rows = padded
    with shared_array(rt, rows, "r") as dev:
        yield dev


def row_parts(rt: Runtime, n: int, cstride: int, itemsize: int = 4) -> list[tuple[int, int]]:
    """The row ranges [r0, r1) in which the kernels take a table of ``n`` rows of ``cstride``
    elements of ``itemsize`` bytes: ``[(0, n)]`` when it fits in one buffer of ``rt``'s device,
    else the fewest ranges of about equal rows that each fit (a contiguous row range of a
    C-contiguous table is read in place, see :func:`device_rows`; the kernels skip the ids outside
    it). BufferLimitError if one row does not fit."""
    row_bytes = itemsize * cstride
    if n * row_bytes <= rt.max_buffer_bytes:
        return [(0, n)]
    check_buffer(rt, row_bytes, f"a row of {cstride} channels ({np.dtype(f'f{itemsize}')})")
    parts = -(-n // (rt.max_buffer_bytes // row_bytes))
    step = -(-n // parts)
    return [(r, min(r + step, n)) for r in range(0, n, step)]


def table_parts(rt: Runtime, table: np.ndarray, cstride: int) -> Iterator[tuple[int, cla.Array]]:
    """Each row part of ``table`` [N, C] (:func:`row_parts`) as (its first row r0, its rows as
    :func:`device_rows`), one at a time: one (0, all rows) when the table fits one buffer."""
    for r0, r1 in row_parts(rt, len(table), cstride, table.itemsize):
        with device_rows(rt, table[r0:r1], cstride) as rows:
            yield r0, rows


@lru_cache(maxsize=None)
def _scan_kernel(context: cl.Context) -> ExclusiveScanKernel:
    return ExclusiveScanKernel(context, np.int32, "a+b", "0")


@lru_cache(maxsize=None)
def device_scan_works(context: cl.Context) -> bool:
    """Whether pyopencl's scan gives numpy's prefix sums on this context's device, checked once
    on 300k values (several work-groups). Its first level reads other work-items' global writes
    after a local barrier only (a race oclgrind reports); PoCL and oclgrind still compute it
    right, other drivers are trusted only after this check."""
    queue = cl.CommandQueue(context)
    values = np.random.default_rng(0).integers(0, 100, 300_001).astype(np.int32)
    dev = cla.to_device(queue, values)
    _scan_kernel(context)(dev, dev)
    ok = np.array_equal(dev.get(), np.cumsum(values) - values)
    if not ok:
        warnings.warn("pyopencl's scan gave wrong prefix sums on this device; qr-cl scans on the host")
    return ok


def exclusive_scan(rt: Runtime, values: cla.Array, out: cla.Array | None = None) -> cla.Array:
    """Exclusive int32 prefix sum of ``values`` into ``out`` (in place when None); returns it.
    pyopencl's scan on the device, or numpy's on the host where :func:`device_scan_works` says no
    or the device has a loop limit (the scan's work-items loop over intervals that grow with the
    array)."""
    out = values if out is None else out
    if rt.loop_limit is None and device_scan_works(rt.context):
        _scan_kernel(rt.context)(values, out)
    else:
        host = values.get()
        out.set(np.cumsum(host, dtype=np.int32) - host)
    return out


def last_value(array: cla.Array) -> int:
    """The last element of a non-empty device array, as a Python int."""
    host = np.empty(1, array.dtype)
    cl.enqueue_copy(array.queue, host, array.base_data,
                    src_offset=array.offset + array.dtype.itemsize * (array.size - 1))
    return int(host[0])
