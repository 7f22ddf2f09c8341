"""Which OpenCL device qr-cl uses, and what it can do: the device choice, the trial kernels a device
must pass, and the probes of its limits (loop iterations, work-group size) and launch shapes.

Device order: ``QR_CL_DEVICE`` (``cpu``, ``gpu``, or ``<platform substring>:<index>``), else
pyopencl's ``PYOPENCL_CTX`` convention, else the first GPU, else the first CPU. A device is used
only after a trial kernel builds and runs on it. The context is created lazily on first use (so a
process may still fork before touching OpenCL; after that, use the ``spawn`` start method).
"""
from __future__ import annotations

import os
import warnings
from functools import lru_cache

import numpy as np
import pyopencl as cl

from .constants import WALK_ALL

NO_OPENCL_HELP = (
    "No OpenCL platform was found. qr-cl runs its kernels through OpenCL; on a CPU-only Debian or "
    "Ubuntu machine install PoCL's CPU driver with `apt-get install -y pocl-opencl-icd` (as root), "
    "or install your GPU vendor's OpenCL driver (an ICD file in /etc/OpenCL/vendors). Do not "
    "install `pyopencl[pocl]` next to Debian's PoCL: its bundled LLVM cannot build kernels for "
    "every CPU. Run `qr-cl devices` afterwards to see what qr-cl will use."
)

_TRIAL_SOURCE = """
__kernel void trial(__global float *x) { int i = get_global_id(0); x[i] = 2.0f * x[i] + 1.0f; }

/* acc = the iterations a work-item really made of a loop of n (ones[] holds 1s the compiler cannot
   see, so the loop is neither folded nor vectorised away). */
/* A kernel with a barrier and local memory: its CL_KERNEL_WORK_GROUP_SIZE is the device's work-group
   limit for such kernels (Mesa 22's llvmpipe: 32, below the 1024 the device reports). */
__kernel void group_probe(__global float *x) {
    __local float t[16];
    t[get_local_id(0) % 16] = x[get_global_id(0)];
    barrier(CLK_LOCAL_MEM_FENCE);
    x[get_global_id(0)] = t[(get_local_id(0) + 1) % 16];
}

__kernel void loop_probe(const int n, __global const int *ones, __global int *acc) {
    int s = 0;
    for (int k = 0; k < n; k++) s += ones[k & 63];
    acc[get_global_id(0)] = s;
}
"""
#: Iterations of the loop probe: qr-cl's walks over a tile's list run this long and longer.
LOOP_PROBE = 1 << 20


class NoDeviceError(RuntimeError):
    """No usable OpenCL device (none installed, or none passed the trial kernel)."""


class DeviceLimitError(NoDeviceError):
    """The device's work-group or local-memory limits are below what a kernel's launch needs."""


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


def device_kind(device: cl.Device) -> str:
    """"gpu", "cpu" or "other" by what the device is: a device reporting several types at once
    (a simulator such as oclgrind reports all of them) is "other"."""
    gpu, cpu = bool(device.type & cl.device_type.GPU), bool(device.type & cl.device_type.CPU)
    return "gpu" if gpu and not cpu else "cpu" if cpu and not gpu else "other"


def _candidates(spec: str | None, pyopencl_ctx: str | None) -> list[cl.Device]:
    """Devices in the order they should be tried for the given QR_CL_DEVICE / PYOPENCL_CTX."""
    devices = list_devices()
    if spec:
        s = spec.strip().lower()
        if s == "cpu":
            chosen = [d for *_, d in devices if device_kind(d) == "cpu"]
        elif s == "gpu":
            chosen = [d for *_, d in devices if device_kind(d) == "gpu"]
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
    order = {"gpu": 0, "cpu": 1, "other": 2}
    return sorted((d for *_, d in devices), key=lambda d: order[device_kind(d)])


def implementation(device: cl.Device) -> str:
    """The device and the OpenCL implementation that runs it, with versions, for messages."""
    platform = device.platform
    return (f"{device.name.strip()} ({platform.name.strip()}, {platform.version.strip()}, "
            f"driver {device.driver_version.strip()})")


def self_check_enabled() -> bool:
    """False when ``QR_CL_SELF_CHECK=off``: devices are then used without the render check (only
    for studying a driver's failures: results are not verified)."""
    value = os.environ.get("QR_CL_SELF_CHECK", "on").strip().lower()
    if value not in ("on", "off"):
        raise ValueError(f"QR_CL_SELF_CHECK={value!r}: use on or off")
    return value == "on"


def trial_run(device: cl.Device) -> str | None:
    """Build and run a tiny kernel on ``device``; None when it works, else the reason."""
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


def forced_loop_limit() -> int | str | None:
    """``QR_CL_LOOP_LIMIT``: an int (walks in windows as on a device that ends loops after that
    many iterations: how the windows run on any device, and a bound for a GPU driver's watchdog),
    ``"none"`` (no limit and no loop probe: for a driver known to run loops whole, such as a
    simulator on which the probe takes a minute), or None when unset; ValueError for another value."""
    value = os.environ.get("QR_CL_LOOP_LIMIT", "").strip().lower()
    if not value:
        return None
    if value == "none":
        return value
    if not value.isdigit() or int(value) < 1024:
        raise ValueError(f"QR_CL_LOOP_LIMIT={value!r}: use an integer >= 1024 (loop iterations per work-item) "
                         "or none")
    return int(value)


@lru_cache(maxsize=None)
def _probed_loop_limit(device: cl.Device) -> int | None:
    ctx = cl.Context([device])
    queue = cl.CommandQueue(ctx)
    prg = cl.Program(ctx, _TRIAL_SOURCE).build()
    ones = cl.Buffer(ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR, hostbuf=np.ones(64, np.int32))
    iterations = np.zeros(64, np.int32)
    acc = cl.Buffer(ctx, cl.mem_flags.READ_WRITE, iterations.nbytes)
    cl.Kernel(prg, "loop_probe")(queue, (64,), None, np.int32(LOOP_PROBE), ones, acc)
    cl.enqueue_copy(queue, iterations, acc)
    queue.finish()
    made = int(iterations.min())
    return None if made >= LOOP_PROBE else made


def loop_limit(device: cl.Device) -> int | None:
    """The loop iterations a work-item of ``device`` makes before its driver ends its loops
    without an error (Mesa 22's llvmpipe: 65535 in all its loops together), or None when a loop
    of LOOP_PROBE iterations ran whole (the loop probe, once per device and process);
    :func:`forced_loop_limit` first. A device with a limit walks its lists in windows
    (:func:`walk_windows`)."""
    forced = forced_loop_limit()
    if forced is None:
        return _probed_loop_limit(device)
    return None if forced == "none" else forced


def walk_windows(limit: int | None, length: int, step_loops: int) -> list[tuple[int, int]]:
    """The windows ``(walk_from, walk_to)`` in which a kernel walks lists of at most ``length``
    steps, each step making at most ``step_loops`` loop iterations: ``[(0, WALK_ALL)]`` (one
    launch) without a loop ``limit``, else windows of ``limit // 2 // step_loops`` steps (half the
    limit left to the loops outside the steps) covering ``length``."""
    if limit is None:
        return [(0, WALK_ALL)]
    step = max(1, limit // 2 // step_loops)
    return [(w, w + step) for w in range(0, max(length, 1), step)]


def choose_device() -> cl.Device:
    """The device qr-cl will use (see module docstring); raises NoDeviceError if none works."""
    reasons = []
    for device in _candidates(os.environ.get("QR_CL_DEVICE"), os.environ.get("PYOPENCL_CTX")):
        reason = trial_run(device)
        if reason is None:
            return device
        reasons.append(f"{implementation(device)}: {reason}")
        warnings.warn(f"OpenCL device {implementation(device)} failed the trial kernels: {reason}")
    raise NoDeviceError("No OpenCL device passed the trial kernels:\n  " + "\n  ".join(reasons))


def gpu_shapes(device: cl.Device) -> bool:
    """Whether work on ``device`` is launched GPU-shaped (``Runtime.gpu_shaped``): on every
    device but a CPU one, unless ``QR_CL_LAUNCH`` (``cpu`` or ``gpu``) says otherwise (that is how
    the GPU shapes run on PoCL); ValueError for another value."""
    forced = os.environ.get("QR_CL_LAUNCH", "").strip().lower()
    if forced not in ("", "cpu", "gpu"):
        raise ValueError(f"QR_CL_LAUNCH={forced!r}: use cpu or gpu")
    return forced == "gpu" if forced else device_kind(device) != "cpu"


def barrier_group_limit(context: cl.Context, device: cl.Device) -> int:
    """The most work-items of a work-group with barriers and local memory that ``device`` runs:
    its limit, or less where a probe kernel's CL_KERNEL_WORK_GROUP_SIZE says so."""
    probe = cl.Kernel(cl.Program(context, _TRIAL_SOURCE).build(), "group_probe")
    return min(int(device.max_work_group_size),
               int(probe.get_work_group_info(cl.kernel_work_group_info.WORK_GROUP_SIZE, device)))
