"""GPU-shaped launches (work-groups over padded sizes, device sorts, many-work-item transposes),
forced on PoCL (``Runtime.gpu_shaped``), give the same bytes as the CPU-shaped ones."""
import numpy as np
import pyopencl.array as cla
import pytest
import torch

import qr_cl
from qr_cl.render import rasterize_plan
from qr_cl.runtime import runtime
from qr_cl.runtime.device import gpu_shapes
from qr_cl.stages import blend_backward, select, transpose


@pytest.fixture(scope="module")
def plan(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    return rasterize_plan(m, q, s, o, v, K, w, h)


def segment_ends(cursor: np.ndarray, chunks: int) -> np.ndarray:
    """The end of each Gaussian's segment from a transpose's cursor [N * chunks]."""
    return cursor.reshape(-1, chunks)[:, -1]


def test_launch_shapes_are_read_once_from_the_environment(monkeypatch):
    device, shaped = runtime().device, runtime().gpu_shaped
    for value, gpu in (("", False), ("gpu", True), (" CPU ", False)):
        monkeypatch.setenv("QR_CL_LAUNCH", value)
        assert gpu_shapes(device) is gpu                     # PoCL: a CPU device
    monkeypatch.setenv("QR_CL_LAUNCH", "tpu")
    with pytest.raises(ValueError, match="QR_CL_LAUNCH"):
        gpu_shapes(device)
    assert runtime().gpu_shaped is shaped                    # the Runtime read it when it was created


@pytest.mark.parametrize("sampler,k", [("volume", 1), ("quantile", 7), ("topk", 5)])
@pytest.mark.parametrize("subset", [False, True])
def test_sorted_transpose_equals_counting_sort(plan, monkeypatch, sampler, k, subset):
    pixels = np.random.default_rng(1).integers(0, (plan.width, plan.height), (300, 2)) if subset else None
    shapes = {}
    for launch in ("cpu", "gpu"):
        monkeypatch.setattr(runtime(), "gpu_shaped", launch == "gpu")
        sel = select(plan, sampler, k, pixels)
        cursor, t_ray, t_w, t_entry, chunks = transpose(sel)
        dimage = np.random.default_rng(2).normal(size=(sel.n_rays, 16)).astype(np.float32)
        grad = blend_backward(sel, cla.to_device(runtime().queue, dimage), 16).get()
        shapes[launch] = segment_ends(cursor.get(), chunks), t_ray.get(), t_w.get(), t_entry.get(), chunks, grad
    (ends, ray, w, entry, chunks, grad), (g_ends, g_ray, g_w, g_entry, g_chunks, g_grad) = shapes["cpu"], shapes["gpu"]
    assert chunks > 1 and g_chunks == 1                 # two different algorithms ...
    np.testing.assert_array_equal(g_ends, ends)         # ... the same transpose
    np.testing.assert_array_equal(g_ray[:ends[-1]], ray[:ends[-1]])
    np.testing.assert_array_equal(g_w[:ends[-1]], w[:ends[-1]])
    np.testing.assert_array_equal(g_entry[:ends[-1]], entry[:ends[-1]])
    assert g_grad.tobytes() == grad.tobytes()


@pytest.mark.parametrize("sampler", ["volume", "quantile", "topk"])
def test_gpu_shaped_render_equals_cpu_shaped(random_scene, monkeypatch, sampler):
    m, q, s, o, v, K, w, h = random_scene
    pixels = np.random.default_rng(3).integers(0, (w, h), (77, 2))
    out = {}
    for launch in ("cpu", "gpu"):
        monkeypatch.setattr(runtime(), "gpu_shaped", launch == "gpu")
        feats = torch.from_numpy(np.random.default_rng(4).normal(size=(len(m), 24)).astype(np.float32))
        feats.requires_grad_(True)
        img, alpha, _ = qr_cl.rasterize(m, q, s, o, feats, v, K, w, h, sampler=sampler, k=6)
        sub, _, _ = qr_cl.rasterize(m, q, s, o, feats, v, K, w, h, sampler=sampler, k=6, pixels=pixels)
        (img.square().sum() + sub.sum()).backward()
        fused, _, meta = qr_cl.render_volume_fused(m, q, s, o, feats.detach(), v, K, w, h)
        rgb, _, _ = qr_cl.rasterize(m, q, s, o, np.ones((len(m), 4, 3), np.float32), v, K, w, h, sh_degree=1)
        out[launch] = [t.detach().numpy().tobytes() for t in (img, alpha, sub, feats.grad, fused, rgb)]
        out[launch].append(meta["flatten_ids"].tobytes())
    assert out["gpu"] == out["cpu"]


def test_pyopencl_scan_and_sort_are_checked_on_the_device(monkeypatch):
    """pyopencl's scan has a global-memory race (a local barrier where a global one is needed,
    reported by oclgrind): GPU-shaped runtimes trust its scan and RadixSort only after checking
    them against numpy once, and scan and sort on the host otherwise."""
    from qr_cl.runtime import exclusive_scan, memory, to_device
    from qr_cl.stages import binning
    rt = runtime()
    assert memory.device_scan_works(rt.context) and binning.device_sort_works(rt.context)   # PoCL
    monkeypatch.setattr(rt, "gpu_shaped", True)
    monkeypatch.setattr(memory, "device_scan_works", lambda context: False)
    monkeypatch.setattr(binning, "device_sort_works", lambda context: False)
    values = np.random.default_rng(0).integers(0, 9, 1000).astype(np.int32)
    np.testing.assert_array_equal(exclusive_scan(rt, to_device(rt, values, np.int32)).get(),
                                  np.cumsum(values) - values)
    keys = np.random.default_rng(1).integers(0, 1 << 40, 1000).astype(np.uint64)
    keys[::7] = keys[3]                                      # ties keep their order (stable)
    k, v = binning.sort_pairs(rt, to_device(rt, keys, np.uint64), to_device(rt, np.arange(1000), np.int32), 40)
    np.testing.assert_array_equal(k.get(), np.sort(keys, kind="stable"))
    np.testing.assert_array_equal(v.get(), np.argsort(keys, kind="stable"))
