"""A device is used only after its self-check: the render check against the float64 twins. The
loop probe measures whether a device's driver ends long loops early without an error (as Mesa 22's
llvmpipe does); such a device walks its lists in windows. Failing devices are refused with a
message naming the implementation and what failed."""
import threading
from pathlib import Path

import pytest

from qr_cl.render import selfcheck
from qr_cl.runtime import Runtime, device, runtime


def test_a_device_that_ends_loops_early_walks_in_windows(monkeypatch, tmp_path):
    whole = device._TRIAL_SOURCE
    cut = whole.replace("for (int k = 0; k < n; k++)", "for (int k = 0; k < min(n, 65535); k++)")
    assert cut != whole
    monkeypatch.setattr(device, "_TRIAL_SOURCE", cut)
    monkeypatch.delenv("QR_CL_LOOP_LIMIT", raising=False)
    device._probed_loop_limit.cache_clear()
    try:
        chosen = device.choose_device()
        assert device.trial_run(chosen) is None                 # used, not refused
        assert device.loop_limit(chosen) == 65535
        rt = Runtime(chosen)
        assert rt.loop_limit == 65535
    finally:
        device._probed_loop_limit.cache_clear()
        monkeypatch.setattr(device, "_TRIAL_SOURCE", whole)
    assert device.loop_limit(chosen) is None                    # PoCL's own loops run whole
    monkeypatch.setenv("QR_CL_LOOP_LIMIT", "4096")
    assert device.loop_limit(chosen) == 4096
    monkeypatch.setattr(device, "_TRIAL_SOURCE", cut)          # "none": no probe, no limit
    device._probed_loop_limit.cache_clear()
    monkeypatch.setenv("QR_CL_LOOP_LIMIT", "None")
    assert device.loop_limit(chosen) is None
    assert device._probed_loop_limit.cache_info().currsize == 0
    monkeypatch.setattr(device, "_TRIAL_SOURCE", whole)
    for bad in ("12", "many"):
        monkeypatch.setenv("QR_CL_LOOP_LIMIT", bad)
        with pytest.raises(ValueError, match="QR_CL_LOOP_LIMIT"):
            device.loop_limit(chosen)


def test_the_render_check_passes_with_walks_in_windows(monkeypatch, tmp_path):
    monkeypatch.setattr(runtime(), "loop_limit", 1024)
    assert selfcheck.render_check() == []


def test_walk_windows_cover_the_longest_list():
    assert device.walk_windows(None, 10_000, 7) == [(0, device.WALK_ALL)]
    windows = device.walk_windows(1024, 1000, 8)               # 64 positions a window
    assert windows[0] == (0, 64) and windows[-1][1] >= 1000 and len(windows) == 16
    assert all(b == c for (_, b), (c, _) in zip(windows, windows[1:]))
    assert device.walk_windows(1024, 0, 8) == [(0, 64)]        # empty lists: one window finishes them


def test_the_render_check_passes_here_and_is_remembered(monkeypatch, tmp_path):
    monkeypatch.setenv("QR_CL_CACHE", str(tmp_path))
    monkeypatch.setattr(selfcheck, "_PASSED", set())
    assert selfcheck.render_check() == []
    assert selfcheck.checked_runtime() is runtime()
    records = list((tmp_path / "checks").glob("*.json"))
    assert len(records) == 1 and "passed" in records[0].read_text()
    monkeypatch.setattr(selfcheck, "_PASSED", set())
    monkeypatch.setattr(selfcheck, "render_check", lambda rt=None: pytest.fail("a remembered pass is checked again"))
    assert selfcheck.checked_runtime() is runtime()


def test_a_pass_of_another_check_is_not_taken_for_one_of_this(monkeypatch, tmp_path):
    """The record of a pass is keyed by the check's own source too: a device that passed an earlier
    check (rendering less) is checked again."""
    rt = runtime()
    here = selfcheck._record(rt)
    edited = tmp_path / "selfcheck.py"
    edited.write_text(Path(selfcheck.__file__).read_text() + "\n# one more render\n")
    monkeypatch.setattr(selfcheck, "__file__", str(edited))
    assert selfcheck._record(rt) != here


def test_a_device_rendering_wrong_rays_is_refused(monkeypatch, tmp_path):
    """As on rusticl, where top-K's walk ends early and leaves rays unselected."""
    monkeypatch.setenv("QR_CL_CACHE", str(tmp_path))
    monkeypatch.setattr(selfcheck, "_PASSED", set())
    rt = runtime()
    launch = type(rt).launch

    def lossy(self, name, *args, **kwargs):
        launch(self, name, *args, **kwargs)
        if name == "select_topk":
            count = kwargs["count"]
            host = count.get()
            host[::3] = 0
            count.set(host)
    monkeypatch.setattr(type(rt), "launch", lossy)
    with pytest.raises(selfcheck.DeviceCheckError) as err:
        selfcheck.checked_runtime()
    message = str(err.value)
    assert "Portable Computing Language" in message and "topk feature gradient" in message
    assert "quantile" not in message and not (tmp_path / "checks").exists()
    with pytest.raises(selfcheck.DeviceCheckError):          # not remembered: checked again
        selfcheck.checked_runtime()
    monkeypatch.setenv("QR_CL_SELF_CHECK", "off")
    assert selfcheck.checked_runtime() is rt


def test_a_device_misreading_half_rows_is_refused(monkeypatch, tmp_path):
    """A driver whose vload_half is wrong renders float16 tables wrong, float32 ones right."""
    monkeypatch.setenv("QR_CL_CACHE", str(tmp_path))
    monkeypatch.setattr(selfcheck, "_PASSED", set())
    rt = runtime()
    launch = type(rt).launch

    def misread(self, name, *args, **kwargs):
        launch(self, name, *args, **kwargs)
        if "HALF_ROWS" in (kwargs.get("defines") or {}):
            kwargs["image"].fill(0)
    monkeypatch.setattr(type(rt), "launch", misread)
    with pytest.raises(selfcheck.DeviceCheckError) as err:
        selfcheck.checked_runtime()
    assert "quantile image of a float16 table" in str(err.value) and "gradient" not in str(err.value)


def test_a_device_misreading_row_parts_is_refused(monkeypatch, tmp_path):
    """A driver whose blend reads a table part's rows as the table's first ones (row0 taken as 0)
    renders tables larger than its buffers wrong: the check reads its wide table in three row parts."""
    monkeypatch.setenv("QR_CL_CACHE", str(tmp_path))
    monkeypatch.setattr(selfcheck, "_PASSED", set())
    rt = runtime()
    launch = type(rt).launch
    parts = []

    def misread(self, name, *args, **kwargs):
        if name == "blend" and kwargs.get("row0"):
            parts.append(kwargs["row0"])
            kwargs["row0"] = 0
        launch(self, name, *args, **kwargs)
    monkeypatch.setattr(type(rt), "launch", misread)
    with pytest.raises(selfcheck.DeviceCheckError) as err:
        selfcheck.checked_runtime()
    message = str(err.value)
    assert "quantile, a table in row parts (256 channels), image" in message, message
    assert "gradient" not in message and "float16" not in message, message
    assert set(parts) == {54, 108}, parts                 # 160 rows in parts of 54, 54 and 52
    assert rt.buffer_cap is None                          # the cap ends with the check


def test_a_buffer_cap_holds_on_its_own_thread_only():
    """The render check caps the buffers on its thread; a render on another thread meanwhile
    plans with the device's own limit."""
    rt = runtime()
    limit = rt.max_buffer_bytes
    seen = []
    with rt.capped_buffers(4096):
        assert rt.max_buffer_bytes == 4096
        other = threading.Thread(target=lambda: seen.append(rt.max_buffer_bytes))
        other.start()
        other.join()
        with rt.capped_buffers(1024):
            assert rt.max_buffer_bytes == 1024
        assert rt.max_buffer_bytes == 4096
    assert seen == [limit] and rt.max_buffer_bytes == limit and rt.buffer_cap is None


def test_self_check_setting_is_validated(monkeypatch):
    monkeypatch.setenv("QR_CL_SELF_CHECK", "maybe")
    with pytest.raises(ValueError, match="QR_CL_SELF_CHECK='maybe': use on or off"):
        device.self_check_enabled()
