"""Host memory of large arrays: allocations checked against the memory the system has available
(a one-line error instead of an OOM kill), and the process-wide pool of large outputs.

:func:`host_empty` takes arrays from the process-wide :class:`HostPool`, which reuses one only
when nothing outside the pool references it any more (no array, view or torch tensor from
``torch.from_numpy``), so an output never aliases memory a caller holds."""
from __future__ import annotations

import math
import os
import sys
import threading

import numpy as np


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
