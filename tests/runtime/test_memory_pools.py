"""Allocation-free calls: pooled device arrays, zero-copy host sharing, and the host pool of large
outputs, which must never hand out memory that a caller still holds."""
from __future__ import annotations

import gc

import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.runtime import (HostPool, Runtime, device_empty, device_rows, runtime, shared_array,
                           trim_device_pool)


def ptr(a) -> int:
    return a.data_ptr() if isinstance(a, torch.Tensor) else a.__array_interface__["data"][0]


def features(n: int, c: int, seed: int, grad: bool = False) -> torch.Tensor:
    f = torch.from_numpy(np.random.default_rng(seed).standard_normal((n, c)).astype(np.float32))
    return f.requires_grad_(grad)


# ---------------------------------------------------------------------------------- host pool

def test_host_pool_reuses_a_buffer_only_when_nothing_references_it():
    pool = HostPool(max_bytes=1 << 24, min_bytes=1024)
    a = pool.empty((256, 64))
    first = ptr(a)
    assert first % HostPool.ALIGN == 0 and a.flags.c_contiguous and a.dtype == np.float32
    del a
    b = pool.empty((256, 64))
    assert ptr(b) == first                                  # freed: reused
    view = torch.from_numpy(b)[3:5, :7]                     # a torch view of a slice outlives b
    del b
    c = pool.empty((256, 64))
    assert ptr(c) != first                                  # still referenced through the view
    kept = np.asarray(c)[::2]                               # a numpy view keeps c's buffer too
    del c
    assert ptr(pool.empty((64, 256))) not in (first,)       # same byte size, both still held
    del view
    d = pool.empty((64, 256))                               # any shape of the same size class
    assert ptr(d) == first
    assert kept.base is not None
    assert pool.hits >= 2


def test_host_pool_stays_within_its_bound():
    pool = HostPool(max_bytes=3 << 20, min_bytes=1024)
    held = [pool.empty(1 << 20, np.uint8)]                  # 1 MiB (+ alignment, size class)
    assert pool.nbytes <= pool.max_bytes
    big = pool.empty(4 << 20, np.uint8)                     # larger than the bound: not pooled
    assert big.nbytes == 4 << 20 and pool.nbytes <= pool.max_bytes
    second = pool.empty(1 << 20, np.uint8)
    assert pool.nbytes <= pool.max_bytes and ptr(second) != ptr(held[0])
    del second
    other = pool.empty((3 << 19) // 4, np.float32)          # 1.5 MiB: evicts the free buffer
    assert pool.nbytes <= pool.max_bytes
    del held, other
    pool.clear()
    assert pool.nbytes == 0
    assert pool.empty(10, np.float32).nbytes == 40          # small arrays are not pooled
    assert pool.nbytes == 0


# --------------------------------------------------------------------------- device memory

def test_device_arrays_come_from_the_runtime_pool():
    rt = runtime()
    a = device_empty(rt, (1000, 16))
    address = a.data.int_ptr
    del a
    b = device_empty(rt, (1000, 16))
    assert b.data.int_ptr == address                        # the freed buffer was reused
    del b
    trim_device_pool(rt, max_held_bytes=0)                  # held buffers released on request
    assert rt.pool.held_blocks == 0


@pytest.mark.skipif(not runtime().host_unified, reason="the device does not share host memory")
def test_zero_copy_rows_and_outputs():
    rt = runtime()
    rows = np.random.default_rng(0).standard_normal((100, 16)).astype(np.float32)
    with device_rows(rt, rows, 16) as dev:                  # float32, contiguous, C == cstride
        assert dev.data.get_host_array(rows.shape, rows.dtype).ctypes.data == rows.ctypes.data
    with device_rows(rt, rows[:, :5], 8) as dev:            # padded: a copy, with zero columns
        assert dev.data.get_host_array((100, 8), np.float32).ctypes.data != rows.ctypes.data
        np.testing.assert_array_equal(dev.get(), np.c_[rows[:, :5], np.zeros((100, 3), np.float32)])
    out = np.zeros((100, 16), np.float32)
    with shared_array(rt, out, "w") as dev:
        assert dev.data.get_host_array(out.shape, out.dtype).ctypes.data == out.ctypes.data
        dev.fill(3.0)
    assert (out == 3).all()


def test_copying_path_when_the_device_does_not_share_host_memory(random_scene, monkeypatch):
    """The buffer-copying path (GPUs, simulators) gives the same bytes as the zero-copy path."""
    m, q, s, o, v, K, w, h = random_scene

    def run():
        f = features(len(m), 40, 3, grad=True)
        img, alpha, _ = qr_cl.rasterize(m, q, s, o, f, v, K, w, h, sampler="quantile", k=6)
        (img * torch.linspace(-1, 1, 40)).sum().backward()
        fused, *_ = qr_cl.render_volume_fused(m, q, s, o, f.detach(), v, K, w, h)
        return img.detach().clone(), alpha.clone(), f.grad.clone(), fused.clone()

    shared = run()
    monkeypatch.setattr(Runtime, "host_unified", property(lambda self: False))
    copied = run()
    for a, b in zip(shared, copied):
        assert torch.equal(a, b)


# ------------------------------------------------------------------- outputs never alias

@pytest.fixture
def fresh_host_pool(monkeypatch):
    """A private host pool for the test (so earlier tests' free buffers do not interfere)."""
    from qr_cl.runtime import host_memory
    pool = HostPool(max_bytes=1 << 28)
    monkeypatch.setattr(host_memory, "_HOST_POOL", pool)
    return pool


def test_a_held_render_is_never_overwritten(random_scene, fresh_host_pool):
    m, q, s, o, v, K, w, h = random_scene
    args = (v, K, w, h)
    first, _, _ = qr_cl.rasterize(m, q, s, o, features(len(m), 64, 0), *args, sampler="quantile", k=8)
    expected = first.clone()
    view = first[10:20, 5:40]                               # keep only a view of the first render
    address = ptr(first)
    del first
    gc.collect()
    second, _, _ = qr_cl.rasterize(m, q, s, o, features(len(m), 64, 1), *args, sampler="quantile", k=8)
    assert ptr(second) != address
    assert torch.equal(view, expected[10:20, 5:40])         # untouched by the second render
    assert not torch.equal(second, expected)
    del view, second
    gc.collect()
    third, _, _ = qr_cl.rasterize(m, q, s, o, features(len(m), 64, 2), *args, sampler="quantile", k=8)
    assert ptr(third) == address                            # reused once nothing held it
    assert fresh_host_pool.hits >= 1


def test_held_gradients_are_never_overwritten(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    f = features(len(m), 64, 0, grad=True)
    render, _, _ = qr_cl.rasterize(m, q, s, o, f, v, K, w, h, sampler="topk", k=5)
    g1 = torch.randn(render.shape, generator=torch.Generator().manual_seed(1))
    g2 = torch.randn(render.shape, generator=torch.Generator().manual_seed(2))
    first = torch.autograd.grad(render, f, g1, retain_graph=True)[0]
    expected = first.clone()
    second = torch.autograd.grad(render, f, g2, retain_graph=True)[0]
    assert ptr(second) != ptr(first) and torch.equal(first, expected)
    again = torch.autograd.grad(render, f, g1)[0]
    assert torch.equal(again, expected)                     # deterministic, and first untouched
    assert torch.equal(first, expected)


def test_outputs_with_padded_rows_are_views(random_scene):
    """C < cstride: the kernels write [P, cstride] rows and the caller gets the [P, C] columns."""
    m, q, s, o, v, K, w, h = random_scene
    f = features(len(m), 5, 0, grad=True)                   # cstride 8
    render, _, _ = qr_cl.rasterize(m, q, s, o, f, v, K, w, h, sampler="quantile", k=4)
    assert render.shape == (h, w, 5) and render.stride()[-2] == 8
    render.sum().backward()
    assert f.grad.shape == f.shape
    ref, _, _ = qr_cl.rasterize(m, q, s, o, f.detach().contiguous().double(), v, K, w, h, sampler="quantile", k=4)
    torch.testing.assert_close(render.detach().double(), ref, rtol=0, atol=0)
