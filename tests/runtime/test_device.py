"""Device choice: QR_CL_DEVICE, trial kernel, and the no-OpenCL message."""
from types import SimpleNamespace

import pyopencl as cl
import pytest

from qr_cl.runtime import context, device


def test_cpu_spec_selects_a_cpu_device(monkeypatch):
    monkeypatch.setenv("QR_CL_DEVICE", "cpu")
    assert device.choose_device().type & cl.device_type.CPU


def test_platform_substring_and_index(monkeypatch):
    (_, _, platform, dev), *_ = device.list_devices()
    monkeypatch.setenv("QR_CL_DEVICE", f"{platform.name.split()[0]}:0")
    assert device.choose_device().int_ptr == dev.int_ptr


def test_unknown_spec_is_a_clear_error(monkeypatch):
    monkeypatch.setenv("QR_CL_DEVICE", "no-such-vendor:3")
    with pytest.raises(device.NoDeviceError, match="matches no OpenCL device.*qr-cl devices"):
        device.choose_device()


def test_no_opencl_names_the_apt_package(monkeypatch):
    def no_platforms():
        raise cl.LogicError("clGetPlatformIDs failed: PLATFORM_NOT_FOUND_KHR")
    monkeypatch.setattr(cl, "get_platforms", no_platforms)
    with pytest.raises(device.NoDeviceError, match="apt-get install -y pocl-opencl-icd"):
        device.choose_device()


def test_a_device_failing_the_trial_is_skipped(monkeypatch):
    (*_, dev), *_ = device.list_devices()
    broken = SimpleNamespace(name="Broken GPU", driver_version="1.0",
                             platform=SimpleNamespace(name="Fake", version="OpenCL 3.0 Fake"))
    working = dev
    monkeypatch.setattr(device, "_candidates", lambda spec, ctx: [broken, working])
    monkeypatch.setattr(device, "trial_run", lambda d: "build failed" if d is broken else None)
    with pytest.warns(UserWarning, match="failed the trial kernels: build failed"):
        assert device.choose_device() is working


def test_trial_kernel_runs_on_the_chosen_device():
    assert device.trial_run(device.choose_device()) is None


def test_two_threads_asking_for_one_program_get_it_built_once(monkeypatch):
    """The training thread and the prefetch thread may ask for the same kernel file at once: the
    program is built once and published whole (a half-filled cache entry gave KeyError), and
    launches from both threads give their own results."""
    import threading
    import time

    import numpy as np
    import pyopencl.array as cla

    rt = context.Runtime(device.choose_device())
    builds, signatures = [], context.kernel_signatures

    def slow_build(source, constants):          # read once per program build
        builds.append(threading.current_thread().name)
        time.sleep(0.2)                         # the other thread arrives while this one builds
        return signatures(source, constants)

    monkeypatch.setattr(context, "kernel_signatures", slow_build)
    start, errors, results = threading.Barrier(2), [], {}

    def spans(length: int) -> None:
        try:
            count = cla.to_device(rt.queue, np.full(64, length, np.int32))
            offsets = cla.to_device(rt.queue, np.arange(64, dtype=np.int32) * length)
            out = cla.empty(rt.queue, 64, np.int32)
            start.wait()
            for _ in range(50):
                rt.launch("ray_spans", 64, n_rays=64, offsets=offsets, count=count, n_entries=64 * length,
                          spans=out)
            results[length] = out.get()
        except Exception as exc:              # reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=spans, args=(length,)) for length in (2, 3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(builds) == 1
    assert (results[2] == 2).all() and (results[3] == 3).all()
