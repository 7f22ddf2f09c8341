"""Device and host memory shared by every stage: feature-row layout, pooled device arrays,
zero-copy host<->device sharing, the host pool of large outputs, and the one exclusive scan.

Features and images live on the device as rows of ``cstride`` floats (see
:func:`channel_layout`); the first ``channels`` floats of a row are meaningful.

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
* large host outputs: :func:`host_empty` takes arrays from the process-wide :class:`HostPool`,
  which reuses one only when nothing outside the pool references it any more (no array, view or
  torch tensor from ``torch.from_numpy``), so an output never aliases memory a caller holds.

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
import sys
import threading
import warnings
from contextlib import contextmanager
from functools import lru_cache
from typing import Iterator

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.scan import ExclusiveScanKernel

from .constants import MAX_CHANNELS, STREAM_MIN_BYTES
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


#: Host allocations from this many bytes on are checked against the memory the system has free.
HOST_CHECK_BYTES = 256 << 20


class HostMemoryError(MemoryError):
    """A large host allocation refused before it is made because the system has not that much
    memory available: the process gets a message naming the sizes instead of an OOM kill."""


def available_host_bytes() -> int | None:
    """The memory the system can give without swapping (Linux: MemAvailable of /proc/meminfo, in
    bytes), or None where it does not say."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) << 10
    except OSError:
        return None
    return None


def check_host_memory(nbytes: int, what: str) -> None:
    """HostMemoryError unless ``nbytes`` (at least HOST_CHECK_BYTES; smaller ones are not
    checked) fit in the host memory available now; ``what`` names the allocation."""
    if nbytes < HOST_CHECK_BYTES:
        return
    available = available_host_bytes()
    if available is not None and nbytes > available:
        raise HostMemoryError(f"{what} needs {nbytes / 1e9:.2f} GB of host memory; the system has "
                              f"{available / 1e9:.2f} GB available (MemAvailable). Render fewer rays at a time "
                              "(pixels=...), fewer channels, or a float16 table")


def check_channels(channels: int) -> None:
    """ValueError unless 1 <= channels <= MAX_CHANNELS."""
    if not 1 <= channels <= MAX_CHANNELS:
        raise ValueError(f"features have {channels} channels; 1..{MAX_CHANNELS} are supported")


#: CPU shapes: the most vectors of a row one work-item blends (512 floats: a whole 512-D row;
#: the kernels accumulate them RV vectors at a time in registers, kernels/common.h), so that each
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


def streamed(nbytes: int) -> int:
    """The ``stream`` argument of the kernels that write an output of ``nbytes`` bytes: 1 (write it
    with non-temporal stores, VSTREAM in kernels/common.h) from STREAM_MIN_BYTES, else 0."""
    return int(nbytes >= STREAM_MIN_BYTES)


def padded_vector(values, channels: int, cstride: int) -> np.ndarray:
    """A float32 [cstride] row holding the first ``channels`` of ``values`` (zeros if None)."""
    out = np.zeros(cstride, np.float32)
    if values is not None:
        out[:channels] = np.asarray(values, np.float32).reshape(-1)[:channels]
    return out


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
    ``HALF_ROWS`` in kernels/common.h), float32 for any other dtype; copied only when they have to be.

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


# ----------------------------------------------------------------------------------------------
# the host pool of large outputs
# ----------------------------------------------------------------------------------------------

def _refs(slots: list, i: int) -> int:
    return sys.getrefcount(slots[i])


#: What :func:`_refs` counts for an array referenced by nothing but the pool's list.
_UNUSED_REFS = _refs([np.empty(1)], 0)


class HostPool:
    """Page-aligned host arrays of at least ``min_bytes`` kept between calls (at most
    ``max_bytes`` in all), so that large outputs of warm calls reuse memory that is already
    mapped instead of page-faulting fresh memory in: glibc maps large allocations (always above
    32 MB; smaller ones too, depending on its adaptive mmap threshold) freshly and returns them
    to the system on free.

    :meth:`empty` hands out a view of a pooled buffer and reuses a buffer only when nothing but
    the pool references it: every numpy view of it references it (``.base``) and a torch tensor
    made by ``torch.from_numpy`` holds its array, so a buffer is free exactly when no array,
    view or tensor of an earlier output is alive (``sys.getrefcount``). Outputs therefore never
    alias memory a caller still holds. Buffer sizes are rounded up to size classes of 1/8 of an
    octave, so requests of slightly varying sizes (e.g. a view's tile keys) share buffers; free
    ones are dropped least recently used first when a new one would exceed ``max_bytes``, and a
    request that still does not fit gets a plain (unpooled) array.
    """

    ALIGN = 4096

    def __init__(self, max_bytes: int, min_bytes: int = 1 << 16) -> None:
        self.max_bytes, self.min_bytes = int(max_bytes), int(min_bytes)
        self._slots: list[np.ndarray] = []       # uint8 owners, least recently used first
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    @property
    def nbytes(self) -> int:
        """Bytes of the buffers the pool owns (free or handed out)."""
        return sum(raw.nbytes for raw in self._slots)

    @property
    def free_bytes(self) -> int:
        """Bytes of the pooled buffers nothing else references (reusable now)."""
        with self._lock:
            return sum(self._slots[i].nbytes for i in range(len(self._slots)) if self._free(i))

    def _free(self, i: int) -> bool:
        return _refs(self._slots, i) <= _UNUSED_REFS

    def clear(self) -> None:
        """Drop the free buffers (those still referenced stay with their holders)."""
        with self._lock:
            self._slots = [self._slots[i] for i in range(len(self._slots)) if not self._free(i)]

    def empty(self, shape, dtype=np.float32) -> np.ndarray:
        """An uninitialised C-contiguous array (page-aligned when pooled); HostMemoryError when a
        fresh one would exceed the memory available (:func:`check_host_memory`)."""
        dtype = np.dtype(dtype)
        shape = (int(shape),) if np.isscalar(shape) else tuple(int(s) for s in shape)
        nbytes = math.prod(shape) * dtype.itemsize
        if nbytes < self.min_bytes:
            return np.empty(shape, dtype)
        what = f"a host array of {shape} {dtype}"
        with self._lock:
            raw = self._take(self.size_class(nbytes + self.ALIGN), what)
        if raw is None:
            check_host_memory(nbytes, what)
            return np.empty(shape, dtype)
        start = -raw.__array_interface__["data"][0] % self.ALIGN
        return raw[start:start + nbytes].view(dtype).reshape(shape)

    def zeros(self, shape, dtype=np.float32) -> np.ndarray:
        """As :meth:`empty`, zero-filled."""
        out = self.empty(shape, dtype)
        out.fill(0)
        return out

    @staticmethod
    def size_class(nbytes: int) -> int:
        """``nbytes`` rounded up to keep its 4 leading bits (at most 1/8 more)."""
        shift = max(nbytes.bit_length() - 4, 0)
        return -(-nbytes >> shift) << shift

    def _take(self, size: int, what: str) -> np.ndarray | None:
        slots = self._slots
        for i in range(len(slots)):
            if slots[i].nbytes == size and self._free(i):
                slots.append(slots.pop(i))                 # most recently used last
                self.hits += 1
                return slots[-1]
        self.misses += 1
        if size > self.max_bytes:
            return None
        total = sum(raw.nbytes for raw in slots)
        i = 0
        while total + size > self.max_bytes and i < len(slots):
            if self._free(i):
                total -= slots.pop(i).nbytes
            else:
                i += 1
        if total + size > self.max_bytes:
            return None
        check_host_memory(size, what)
        slots.append(np.empty(size, np.uint8))
        return slots[-1]


_HOST_POOL: HostPool | None = None


def host_pool() -> HostPool:
    """The process-wide :class:`HostPool`, bounded by ``$QR_CL_HOST_POOL_MB`` MiB (default 2048:
    two whole-image 512-D renders of 640x480, the previous one still held by the caller)."""
    global _HOST_POOL
    if _HOST_POOL is None:
        _HOST_POOL = HostPool(int(os.environ.get("QR_CL_HOST_POOL_MB", 2048)) << 20)
    return _HOST_POOL


def host_empty(shape, dtype=np.float32) -> np.ndarray:
    """An uninitialised host array for a large output, from :func:`host_pool` (memory of an
    earlier output nobody references any more; small arrays are plain ``np.empty``)."""
    return host_pool().empty(shape, dtype)


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
