"""Device choice: QR_CL_DEVICE, trial kernel, and the no-OpenCL message."""
from types import SimpleNamespace

import pyopencl as cl
import pytest

from qr_cl.runtime import device


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
