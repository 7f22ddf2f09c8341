"""The process's resources as the commands set them: cores for the kernels, torch's threads, and
glibc's handling of freed memory."""
from __future__ import annotations

import ctypes
import ctypes.util
import functools
import os
from contextlib import contextmanager

import torch


def process_cores() -> int:
    """Cores this process may use: its CPU affinity (``os.sched_getaffinity``) shared evenly
    among the ranks of a torchrun job on this machine (``LOCAL_WORLD_SIZE``), at least 1."""
    return max(1, len(os.sched_getaffinity(0)) // max(1, int(os.environ.get("LOCAL_WORLD_SIZE", "1"))))


def cap_kernel_threads() -> int:
    """Give PoCL (the CPU OpenCL driver) the cores this process may use (:func:`process_cores`):
    ``POCL_MAX_PTHREAD_COUNT``, unless already set. PoCL reads it when the OpenCL platform is
    first touched, so call this before anything renders (the CLI's train, demo and reproduce do).
    Returns the value in force.

    The kernels and torch take turns: the thread that launches a kernel waits for it, and the
    sparse convolutions run while no kernel does (:mod:`qr_cl.app.training.trainer`); only the next step's
    selections (geometry) run beside the blend, on the same PoCL workers. So a worker per core
    measured faster for a training step than one worker, though it suffers more when other
    processes keep the cores busy.
    """
    os.environ.setdefault("POCL_MAX_PTHREAD_COUNT", str(process_cores()))
    return int(os.environ["POCL_MAX_PTHREAD_COUNT"])


#: glibc mallopt parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
#: Allocations below this come from malloc's heaps rather than fresh mmaps (the largest mallopt takes).
HEAP_ALLOC_MAX = (1 << 31) - 1


@functools.cache
def _libc() -> ctypes.CDLL:
    """The C library, loaded once."""
    return ctypes.CDLL(ctypes.util.find_library("c"))


def keep_freed_memory() -> bool:
    """Make glibc's malloc keep freed memory for the next allocation instead of returning it to
    the system: large blocks from its heaps, not from a fresh mmap each (``M_MMAP_THRESHOLD``),
    and no trimming of the heap top (``M_TRIM_THRESHOLD``). A training step allocates and frees
    the same torch temporaries (activations of the UNet, the loss's [rays, C] arrays) every step,
    and each fresh mmap of them is faulted in again, 2 MB pages cleared by the kernel under
    transparent huge pages. The process keeps its peak heap until :func:`release_freed_memory`
    (the demo and reproduce call it between their phases), so the CLI's train, demo and reproduce
    call this, never the library. Returns False where the C library has no mallopt (not glibc),
    changing nothing.

    With it a training step measured less system time and fewer page faults (``qr-cl train``)."""
    mallopt = getattr(_libc(), "mallopt", None)
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, HEAP_ALLOC_MAX)) & bool(mallopt(_M_TRIM_THRESHOLD, HEAP_ALLOC_MAX))


def release_freed_memory() -> bool:
    """Give back to the system what the process keeps for reuse, between the phases of a long
    command (the demo's training runs, evaluations and pictures): the device pool's held buffers
    (:func:`~qr_cl.runtime.trim_device_pool`), the host pool's free arrays
    (:func:`~qr_cl.runtime.host_pool`) and the free pages of glibc's heaps (``malloc_trim``), which
    :func:`keep_freed_memory` otherwise keeps for the process's lifetime. So a command's peak is
    its largest phase's, not the sum of what its phases left behind; the next phase faults its
    pages in once more. Returns False where the C library has no malloc_trim (the pools are
    emptied all the same)."""
    from ..runtime import host_pool, runtime, trim_device_pool

    trim_device_pool(runtime(), 0)
    host_pool().clear()
    trim = getattr(_libc(), "malloc_trim", None)
    if trim is None:
        return False
    trim(0)
    return True


@contextmanager
def torch_threads(n: int):
    """Run the block with ``n`` torch intra-op threads (restored after). One thread is the default
    for training: PoCL renders with its own threads, and torch's OpenMP workers spin badly when the
    cores are shared (beside other busy processes, 2 threads made a step many times slower than 1,
    with libgomp's default spinning and, less so, with ``OMP_WAIT_POLICY=PASSIVE``). Torch's
    results depend on the thread count, so it is fixed for a run, never adapted to the load."""
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)
