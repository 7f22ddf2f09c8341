"""GPU-shaped launches (the tile walk, GPU blends, device sorts, many-work-item transposes),
forced on PoCL (``Runtime.gpu_shaped``), give the same bytes as the CPU-shaped ones; so do walks
in windows (``Runtime.loop_limit``, as on a device whose driver ends long loops)."""
import numpy as np
import pyopencl.array as cla
import pytest
import torch

import qr_cl
from qr_cl.render import rasterize_plan
from qr_cl.runtime import Runtime, runtime
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
        cursor, t_ray, t_w, t_entry, chunks, _ = transpose(sel)
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


def every_path(scene) -> dict[str, bytes]:
    """The bytes of every public path's outputs on ``scene``: rasterize with each sampler (image,
    alpha, feature gradient) and at a pixel subset, a float16 table, render_volume_fused, and
    rasterization's gradients w.r.t. the Gaussians."""
    m, q, s, o, v, K, w, h = scene
    rng = np.random.default_rng(4)
    feats = rng.normal(size=(len(m), 24)).astype(np.float32)
    weights = torch.from_numpy(rng.normal(size=(h, w, 24)).astype(np.float32))
    pixels = rng.integers(0, (w, h), (300, 2))
    out = {}
    for sampler in ("volume", "quantile", "topk", "stratified"):
        for px in (None, pixels):
            f = torch.from_numpy(feats).requires_grad_(True)
            img, alpha, _ = qr_cl.rasterize(m, q, s, o, f, v, K, w, h, sampler=sampler, k=6, pixels=px)
            (img * (weights if px is None else weights[px[:, 1], px[:, 0]])).sum().backward()
            for name, t in (("image", img), ("alpha", alpha), ("dfeatures", f.grad)):
                out[f"{sampler}/{px is None}/{name}"] = t.detach().numpy().tobytes()
    f = torch.from_numpy(feats).half().requires_grad_(True)
    img, _, _ = qr_cl.rasterize(m, q, s, o, f, v, K, w, h, sampler="quantile", k=6)
    (img * weights).sum().backward()
    out["half"], out["half/d"] = img.detach().numpy().tobytes(), f.grad.numpy().tobytes()
    fused, alpha, meta = qr_cl.render_volume_fused(m, q, s, o, feats, v, K, w, h, background=np.ones(24))
    out["fused"] = fused.numpy().tobytes() + alpha.numpy().tobytes() + meta["depth"].tobytes()
    params = [torch.from_numpy(np.asarray(a, np.float32)).requires_grad_(True) for a in (m, q, s, o, feats[:, :3])]
    img, _, _ = qr_cl.rasterization(*params, torch.from_numpy(v[None]), torch.from_numpy(K[None]), w, h, k=6)
    (img[0] * weights[..., :3]).sum().backward()
    out["rasterization"] = img.detach().numpy().tobytes() + b"".join(p.grad.numpy().tobytes() for p in params)
    return out


def test_walk_windows_and_launch_shapes_give_the_same_bytes(random_scene, monkeypatch):
    """Each pair of launch shape and loop limit (None: one launch per walk; 64: windows of a few
    list positions, the rays' state kept between launches) renders every path with the same bytes,
    and the windowed runs did launch walks past their first window."""
    rt = runtime()
    windows = []
    launch = Runtime.launch

    def counted(self, name, *args, walk_from=None, **kwargs):
        if walk_from is not None:
            windows.append((name, walk_from))
            kwargs["walk_from"] = walk_from
        launch(self, name, *args, **kwargs)
    monkeypatch.setattr(Runtime, "launch", counted)
    runs = {}
    for shape in ("cpu", "gpu"):
        for limit in (None, 64):
            monkeypatch.setattr(rt, "gpu_shaped", shape == "gpu")
            monkeypatch.setattr(rt, "loop_limit", limit)
            windows.clear()
            runs[shape, limit] = every_path(random_scene)
            resumed = {name for name, walk_from in windows if walk_from > 0}
            if limit:
                prefix = "tile_" if shape == "gpu" else ""
                assert {f"{prefix}vrender", "blend_backward_group" if shape == "gpu" else "blend_backward",
                        "weight_grads", "splat_backward"} | {
                        f"{prefix}{'select_' if not prefix else ''}{s}" for s in ("quantile", "topk", "stratified")} \
                    <= resumed, resumed
            else:
                assert not resumed
    want = runs["cpu", None]
    for key, got in runs.items():
        assert got.keys() == want.keys()
        assert [k for k in want if got[k] != want[k]] == [], key
