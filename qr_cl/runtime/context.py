"""The Runtime: one OpenCL context and in-order queue on the chosen device, its memory pool, the
programs built from qr-cl's kernels (cached per file and defines), and the launcher that calls a
kernel by name with its arguments by name."""
from __future__ import annotations

import threading
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import pyopencl.tools as cl_tools

from .constants import KERNEL_CONSTANTS, TILE
from .device import (DeviceLimitError, barrier_group_limit, choose_device, device_kind, gpu_shapes, implementation,
                     loop_limit)
from .signatures import KernelArg, SignatureError, kernel_signatures
from .sources import kernel_files, kernel_source

#: Work-group size of GPU-shaped launches (a multiple of every vendor's SIMD width: 32 or 64).
GROUP_SIZE = 64
#: Local memory of the GPU-shaped kernels: bytes per ray of a tile walk's batch (an id and a
#: splat, kernels/walk.h TILE_WALK) and per work-item of a GPU blend (group_blend in blend.cl:
#: a row's start and count, GROUP_ENTRIES = 16 staged ids and weights).
TILE_WALK_BYTES_PER_RAY = 4 + 32
GROUP_BLEND_BYTES_PER_ITEM = 8 + 16 * 8
#: The rays of a tile walk's work-group: the largest of these the device allows (TILE * TILE,
#: a whole tile, where it can; each divides it).
GROUP_RAYS_CHOICES = (TILE * TILE, 128, 64, 32, 16)

#: Work-group size of the lane kernels, whose work-items hold TILE-wide vectors of rays or Gaussians
#: (select.cl, vrender.cl, project.cl): PoCL runs the work-items of a group on one thread's stack,
#: and its default groups of up to 4096 overflow it with their private arrays (garbage or a crash on
#: a 640x480 image), so the size is set, not left to the driver.
BLOCK_GROUP = (TILE,)


def bind(kernel: str, arg: KernelArg, x):
    """The value pyopencl passes for ``x`` as argument ``arg`` of ``kernel``: a buffer (device
    array, Buffer or None) or a numpy scalar/vector of the declared type (3-vectors as 4)."""
    if arg.is_buffer:
        if x is None or isinstance(x, cl.MemoryObjectHolder):
            return x
        if isinstance(x, cla.Array):
            if x.dtype != arg.dtype:
                raise TypeError(f"{kernel}({arg.name}): a {arg.type_name} buffer needs {arg.dtype} data, "
                                f"got {x.dtype}")
            return x.data
        raise TypeError(f"{kernel}({arg.name}): expected a device array or buffer, got {type(x).__name__}")
    if arg.space:
        raise TypeError(f"{kernel}({arg.name}): {arg.space} pointer arguments are not supported")
    if arg.lanes > 1:
        v = np.zeros(4 if arg.lanes == 3 else arg.lanes, arg.dtype)
        v[:arg.lanes] = np.asarray(x, arg.dtype).reshape(-1)
        return v
    return arg.dtype.type(x)



@dataclass
class Runtime:
    """One OpenCL context + in-order queue, with programs cached per (file, defines).

    Kernels are called by name with their arguments by name (:meth:`launch`): the argument list
    is the one the kernel's source declares (:mod:`qr_cl.runtime.signatures`), so no call site
    repeats it and programs a driver loads from a binary cache work as well.
    ``pool`` is the device memory pool every per-call device array comes from (see
    :func:`qr_cl.runtime.device_empty`): buffers freed by one call are reused by the next.
    ``gpu_shaped``: launch GPU-shaped work (work-groups of :data:`GROUP_SIZE` over padded global
    sizes, device sorts, many-work-item transposes) rather than CPU-shaped work (host sorts, a
    few long work-items); set from :func:`gpu_shapes` when the Runtime is created, and settable
    (that is how tests run both shapes on one device). ``loop_limit``: the loop iterations a
    work-item may make on this device (:func:`loop_limit`; None: no limit), by which kernels
    walk their lists in windows (:func:`walk_windows`); settable like ``gpu_shaped``.
    ``group_limit``: the most work-items of a work-group with barriers the device runs (the
    device's limit, or less: a probe kernel's CL_KERNEL_WORK_GROUP_SIZE).
    :meth:`capped_buffers` makes :attr:`max_buffer_bytes` report less on the calling thread, so
    that its tables and ray sets are split as on a device with smaller buffers (the render check
    splits a table on every device with it; other threads' renders are not affected).
    """

    device: cl.Device
    context: cl.Context = field(init=False)
    queue: cl.CommandQueue = field(init=False)
    pool: cl_tools.MemoryPool = field(init=False, repr=False)
    gpu_shaped: bool = field(init=False)
    loop_limit: int | None = field(init=False)
    group_limit: int = field(init=False)
    _caps: threading.local = field(init=False, default_factory=threading.local, repr=False)
    _programs: dict = field(init=False, default_factory=dict)
    _group_limits: dict = field(init=False, default_factory=dict, repr=False)
    _build_lock: threading.Lock = field(init=False, default_factory=threading.Lock, repr=False)
    _launch_lock: threading.Lock = field(init=False, default_factory=threading.Lock, repr=False)

    def __post_init__(self) -> None:
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context)
        self.pool = cl_tools.MemoryPool(cl_tools.ImmediateAllocator(self.queue))
        self.gpu_shaped = gpu_shapes(self.device)
        self.loop_limit = loop_limit(self.device)
        self.group_limit = barrier_group_limit(self.context, self.device)

    @property
    def narrow_rows(self) -> bool:
        """Whether a blend work-item takes one vector of a row (GPU shapes, and devices with a
        loop limit, whose loops over a row's chunks would add up) rather than up to
        CPU_ROW_VECTORS (:func:`qr_cl.runtime.channel_layout`)."""
        return self.gpu_shaped or self.loop_limit is not None

    def _group_size(self, choices: tuple[int, ...], local_bytes: int, what: str) -> int:
        """The largest of ``choices`` that the device's work-group and local-memory limits allow
        for work-groups using ``local_bytes`` per work-item; DeviceLimitError naming the device
        and its limits when none does."""
        local = int(self.device.local_mem_size)
        for size in choices:
            if size <= self.group_limit and size * local_bytes + 64 <= local:
                return size
        raise DeviceLimitError(
            f"{implementation(self.device)} allows work-groups of {self.group_limit} work-items "
            f"and {local} bytes of local memory; {what} need work-groups of {choices[-1]} with "
            f"{choices[-1] * local_bytes + 64} bytes")

    @property
    def group_rays(self) -> int:
        """The rays of a tile walk's work-group (``GROUP_RAYS`` of kernels/walk.h)."""
        return self._group_size(GROUP_RAYS_CHOICES, TILE_WALK_BYTES_PER_RAY, "qr-cl's tile walks")

    @property
    def blend_group(self) -> int:
        """The work-items of a GPU blend's work-group (``BLEND_GROUP`` of kernels/blend.cl)."""
        return self._group_size((GROUP_SIZE, 32, 16, 8), GROUP_BLEND_BYTES_PER_ITEM, "qr-cl's GPU blends")

    @property
    def max_buffer_bytes(self) -> int:
        """The largest single buffer this device allows (CL_DEVICE_MAX_MEM_ALLOC_SIZE), bytes, or
        the calling thread's :attr:`buffer_cap` where that is smaller."""
        limit = int(self.device.max_mem_alloc_size)
        return limit if self.buffer_cap is None else min(limit, self.buffer_cap)

    @property
    def buffer_cap(self) -> int | None:
        """The calling thread's cap on :attr:`max_buffer_bytes` (:meth:`capped_buffers`), or None."""
        return getattr(self._caps, "nbytes", None)

    @contextmanager
    def capped_buffers(self, nbytes: int) -> Iterator[None]:
        """Within the block, this thread plans buffers as if the device allowed at most ``nbytes``
        in one; the previous cap is restored after."""
        old, self._caps.nbytes = self.buffer_cap, nbytes
        try:
            yield
        finally:
            self._caps.nbytes = old

    @property
    def is_cpu(self) -> bool:
        """True for a CPU device (the host is the device: host-side sorting pays off)."""
        return device_kind(self.device) == "cpu"

    @property
    def host_unified(self) -> bool:
        """True when kernels can work in host memory directly (CL_DEVICE_HOST_UNIFIED_MEMORY on a
        CPU or GPU device): host arrays are then wrapped in USE_HOST_PTR buffers instead of copied
        (:func:`qr_cl.runtime.shared_array`). False for devices that report several types (a
        simulator such as oclgrind), which get the buffer-copying path."""
        if device_kind(self.device) == "other":
            return False
        try:
            return bool(self.device.host_unified_memory)
        except cl.Error:
            return self.is_cpu

    @property
    def accumulator_floats(self) -> int:
        """Floats of a feature row a blend loop keeps in registers at a time (``ACC_FLOATS`` of
        kernels/rows.h): about half the vector register file, from the native float vector
        width: 16 lanes (AVX-512: 32 registers) give 256, 8 lanes (AVX2: 16 registers) 64, 4
        lanes (SSE, NEON) 32. More spills the accumulators to the stack."""
        width = max(1, int(self.device.native_vector_width_float))
        return width * width if width >= 8 else 8 * width

    @property
    def build_constants(self) -> dict[str, object]:
        """The defines every program of this runtime is built with: the shared constants
        (:data:`KERNEL_CONSTANTS`), ``ACC_FLOATS``, ``GROUP_RAYS`` and ``BLEND_GROUP``."""
        return {**KERNEL_CONSTANTS, "ACC_FLOATS": self.accumulator_floats, "GROUP_RAYS": self.group_rays,
                "BLEND_GROUP": self.blend_group}

    def kernel(self, name: str, **defines: int | float) -> tuple[cl.Kernel, tuple[KernelArg, ...]]:
        """The kernel ``name`` built with ``-D KEY=VALUE`` per define (on top of
        :attr:`build_constants`), with the arguments its source declares
        (checked against the built kernel's count). Programs and kernel objects are cached; a
        program is built once, under a lock, and published whole, so threads may ask at once."""
        file = kernel_files().get(name)
        if file is None:
            raise KeyError(f"no kernel named {name!r} in qr_cl.kernels")
        key = (file, tuple(sorted(defines.items())))
        kernels = self._programs.get(key)
        if kernels is None:
            with self._build_lock:               # one build per program, published whole
                kernels = self._programs.get(key)
                if kernels is None:
                    kernels = self._programs[key] = self._build(file, defines)
        return kernels[name]

    def _build(self, file: str, defines: dict) -> dict[str, tuple[cl.Kernel, tuple[KernelArg, ...]]]:
        """{kernel name: (kernel, declared arguments)} of ``file`` built with ``defines``."""
        constants = {**self.build_constants, **defines}
        source = kernel_source(file)
        with warnings.catch_warnings():          # some compilers (Intel's) always return a build log
            warnings.simplefilter("ignore", cl.CompilerWarning)
            program = cl.Program(self.context, source).build(
                options=[f"-D{k}={v}" for k, v in sorted(constants.items())])
        declared = kernel_signatures(source, constants)
        kernels = {}
        for k in program.all_kernels():
            args = declared[k.function_name]
            if len(args) != k.num_args:
                raise SignatureError(f"kernel {k.function_name} ({file}): the source declares {len(args)} "
                                     f"arguments, the built program {k.num_args}")
            kernels[k.function_name] = (k, args)
        return kernels

    def launch(self, name: str, global_size: int | tuple[int, ...], defines: dict | None = None,
               local_size: tuple[int, ...] | None = None, **args) -> None:
        """Enqueue kernel ``name`` over ``global_size`` work-items with its arguments by name.

        Device arrays are checked against the declared element type, scalars converted to it;
        a missing or unknown argument raises TypeError naming the kernel. Without ``local_size``
        a GPU-shaped runtime (:attr:`gpu_shaped`) runs work-groups of GROUP_SIZE over the first
        dimension padded up to a multiple of it (every kernel returns early past its own count);
        a CPU-shaped one leaves the grouping to the driver. Setting the arguments and enqueueing
        happen under a lock (a kernel object is shared by the threads that launch it).
        """
        kernel, declared = self.kernel(name, **(defines or {}))
        names = [a.name for a in declared]
        missing, unknown = [n for n in names if n not in args], [n for n in args if n not in names]
        if missing or unknown:
            raise TypeError(f"kernel {name}({', '.join(names)}): missing {missing}, unknown {unknown}")
        size = (global_size,) if isinstance(global_size, int) else tuple(global_size)
        if local_size is None and self.gpu_shaped:
            group = min(GROUP_SIZE, self.group_limit)
            local_size = (group,) + (1,) * (len(size) - 1)
            size = (-(-size[0] // group) * group,) + size[1:]
        if local_size is not None:
            self._check_group(name, kernel, int(np.prod(local_size)))
        bound = [bind(name, a, args[a.name]) for a in declared]
        with self._launch_lock:                  # a kernel object's arguments are not thread-safe
            kernel(self.queue, size, local_size, *bound)

    def _check_group(self, name: str, kernel: cl.Kernel, items: int) -> None:
        """DeviceLimitError naming the device when ``kernel`` cannot run work-groups of ``items``
        work-items on it (CL_KERNEL_WORK_GROUP_SIZE: the device's limit, or less for a kernel
        that needs many registers)."""
        limit = self._group_limits.get(kernel.int_ptr)
        if limit is None:
            limit = self._group_limits[kernel.int_ptr] = kernel.get_work_group_info(
                cl.kernel_work_group_info.WORK_GROUP_SIZE, self.device)
        if items > limit:
            raise DeviceLimitError(f"{implementation(self.device)} runs kernel {name} in work-groups of at most "
                                   f"{limit} work-items; qr-cl launches it in work-groups of {items}")


_RUNTIME: Runtime | None = None


def runtime() -> Runtime:
    """The process-wide Runtime, created on first use."""
    global _RUNTIME
    if _RUNTIME is None:
        _RUNTIME = Runtime(choose_device())
    return _RUNTIME
