"""OpenCL device choice, context/queue ownership, and the program/kernel build cache.

Device order: ``QR_CL_DEVICE`` (``cpu``, ``gpu``, or ``<platform substring>:<index>``), else
pyopencl's ``PYOPENCL_CTX`` convention, else the first GPU, else the first CPU. A device is used
only after a trial kernel builds and runs on it. The context is created lazily on first use (so a
process may still fork before touching OpenCL; after that, use the ``spawn`` start method).
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass, field
from importlib import resources

import numpy as np
import pyopencl as cl

NO_OPENCL_HELP = (
    "No OpenCL platform was found. qr-cl runs its kernels through OpenCL; on a CPU-only Debian or "
    "Ubuntu machine install PoCL's CPU driver with `apt-get install -y pocl-opencl-icd` (as root), "
    "or install your GPU vendor's OpenCL driver (an ICD file in /etc/OpenCL/vendors). Do not "
    "install `pyopencl[pocl]` next to Debian's PoCL: its bundled LLVM cannot build kernels for "
    "every CPU. Run `qr-cl devices` afterwards to see what qr-cl will use."
)

_TRIAL_SOURCE = """
__kernel void trial(__global float *x) { int i = get_global_id(0); x[i] = 2.0f * x[i] + 1.0f; }
"""


class NoDeviceError(RuntimeError):
    """No usable OpenCL device (none installed, or none passed the trial kernel)."""


def list_devices() -> list[tuple[int, int, cl.Platform, cl.Device]]:
    """All OpenCL devices as (platform index, device index, platform, device).

    Raises NoDeviceError with install advice when no OpenCL platform exists.
    """
    try:
        platforms = cl.get_platforms()
    except cl.Error as exc:  # PLATFORM_NOT_FOUND_KHR when no ICD is installed
        raise NoDeviceError(NO_OPENCL_HELP) from exc
    found = []
    for pi, platform in enumerate(platforms):
        try:
            devices = platform.get_devices()
        except cl.Error:
            continue
        found.extend((pi, di, platform, dev) for di, dev in enumerate(devices))
    if not found:
        raise NoDeviceError(NO_OPENCL_HELP)
    return found


def _is_gpu(device: cl.Device) -> bool:
    return bool(device.type & cl.device_type.GPU)


def _candidates(spec: str | None, pyopencl_ctx: str | None) -> list[cl.Device]:
    """Devices in the order they should be tried for the given QR_CL_DEVICE / PYOPENCL_CTX."""
    devices = list_devices()
    if spec:
        s = spec.strip().lower()
        if s == "cpu":
            chosen = [d for *_, d in devices if d.type & cl.device_type.CPU]
        elif s == "gpu":
            chosen = [d for *_, d in devices if _is_gpu(d)]
        else:
            name, _, index = s.rpartition(":") if ":" in s else (s, "", "")
            matching = [d for _, _, p, d in devices if name in p.name.lower() or name in d.name.lower()]
            if index:
                if not index.isdigit():
                    raise NoDeviceError(f"QR_CL_DEVICE={spec!r}: the part after ':' must be a device index")
                matching = matching[int(index):int(index) + 1]
            chosen = matching
        if not chosen:
            raise NoDeviceError(
                f"QR_CL_DEVICE={spec!r} matches no OpenCL device; `qr-cl devices` lists the devices "
                "(use cpu, gpu, or <platform substring>:<index>)")
        return chosen
    if pyopencl_ctx:
        parts = pyopencl_ctx.split(":")
        try:
            platform = cl.get_platforms()[int(parts[0])]
            devs = platform.get_devices()
            return [devs[int(parts[1])]] if len(parts) > 1 and parts[1] else devs
        except (ValueError, IndexError) as exc:
            raise NoDeviceError(f"PYOPENCL_CTX={pyopencl_ctx!r} names no device") from exc
    gpus = [d for *_, d in devices if _is_gpu(d)]
    others = [d for *_, d in devices if not _is_gpu(d)]
    return gpus + others


def trial_run(device: cl.Device) -> str | None:
    """Build and run a tiny kernel on ``device``; return None when it works, else the reason."""
    try:
        ctx = cl.Context([device])
        queue = cl.CommandQueue(ctx)
        prg = cl.Program(ctx, _TRIAL_SOURCE).build()
        host = np.arange(64, dtype=np.float32)
        buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=host)
        cl.Kernel(prg, "trial")(queue, (64,), None, buf)
        out = np.empty_like(host)
        cl.enqueue_copy(queue, out, buf)
        queue.finish()
    except cl.Error as exc:
        return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else exc}"
    if not np.array_equal(out, 2 * host + 1):
        return "trial kernel ran but returned wrong values"
    return None


def choose_device() -> cl.Device:
    """The device qr-cl will use (see module docstring); raises NoDeviceError if none works."""
    reasons = []
    for device in _candidates(os.environ.get("QR_CL_DEVICE"), os.environ.get("PYOPENCL_CTX")):
        reason = trial_run(device)
        if reason is None:
            return device
        reasons.append(f"{device.name.strip()} ({device.platform.name.strip()}): {reason}")
        warnings.warn(f"OpenCL device {device.name.strip()!r} failed the trial kernel: {reason}")
    raise NoDeviceError("No OpenCL device passed the trial kernel:\n  " + "\n  ".join(reasons))


def kernel_source(name: str) -> str:
    """Text of ``kernels/<name>`` with ``common.h`` inlined (so driver caches see header edits)."""
    root = resources.files("qr_cl.kernels")
    text = (root / name).read_text()
    header = (root / "common.h").read_text()
    return text.replace('#include "common.h"', header)


@dataclass
class Runtime:
    """One OpenCL context + in-order queue, with programs cached per (file, defines)."""

    device: cl.Device
    context: cl.Context = field(init=False)
    queue: cl.CommandQueue = field(init=False)
    _kernels: dict = field(init=False, default_factory=dict)

    def __post_init__(self) -> None:
        self.context = cl.Context([self.device])
        self.queue = cl.CommandQueue(self.context)

    @property
    def is_cpu(self) -> bool:
        return bool(self.device.type & cl.device_type.CPU)

    def kernel(self, file: str, name: str, **defines: int | float) -> cl.Kernel:
        """The kernel ``name`` from ``kernels/<file>`` built with ``-D KEY=VALUE`` per define.

        Kernel objects are cached: ``prg.name`` would create a new one on every access.
        """
        key = (file, tuple(sorted(defines.items())))
        if key not in self._kernels:
            options = [f"-D{k}={v}" for k, v in sorted(defines.items())]
            program = cl.Program(self.context, kernel_source(file)).build(options=options)
            self._kernels[key] = {k.function_name: k for k in program.all_kernels()}
        return self._kernels[key][name]


_RUNTIME: Runtime | None = None


def runtime() -> Runtime:
    """The process-wide Runtime, created on first use."""
    global _RUNTIME
    if _RUNTIME is None:
        _RUNTIME = Runtime(choose_device())
    return _RUNTIME
