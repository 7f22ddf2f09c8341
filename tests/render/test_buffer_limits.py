"""Renders larger than the device's largest buffer: split into sets of rays and groups of channels
(the same image), or refused with a message naming the sizes and the limit."""
import numpy as np
import pytest
import torch

import pyopencl as cl

import qr_cl
from qr_cl.runtime import BufferLimitError, Runtime

ALLOCATE = cl.tools.MemoryPool.__call__


def limit_buffers(monkeypatch, nbytes: int) -> None:
    """Make the device's largest buffer ``nbytes``, and fail any buffer made larger than that
    (as a driver would: rusticl's INVALID_BUFFER_SIZE)."""
    monkeypatch.setattr(Runtime, "max_buffer_bytes", property(lambda self: nbytes))
    def checked(pool, size):
        assert size <= nbytes, f"a {size}-byte buffer escaped the {nbytes}-byte limit"
        return ALLOCATE(pool, size)
    monkeypatch.setattr(cl.tools.MemoryPool, "__call__", checked)


def render(scene, channels: int, sampler: str, k: int = 6, pixels=None):
    m, q, s, o, v, K, w, h = scene
    feats = torch.from_numpy(np.random.default_rng(channels).normal(size=(len(m), channels)).astype(np.float32))
    feats.requires_grad_(True)
    img, alpha, meta = qr_cl.rasterize(m, q, s, o, feats, v, K, w, h, sampler=sampler, k=k, pixels=pixels,
                                       background=torch.linspace(-1, 1, channels))
    (img * torch.linspace(0, 1, img.shape[-1])).sum().backward()
    return img.detach(), alpha, feats.grad, meta["selection"]


@pytest.fixture(params=["cpu", "gpu"])
def shape(request, monkeypatch):
    """Both launch shapes (GPU shapes sort 8-byte transpose keys per selection entry)."""
    monkeypatch.setattr(qr_cl.runtime.runtime(), "gpu_shaped", request.param == "gpu")
    return request.param


@pytest.mark.parametrize("sampler", ["volume", "quantile", "topk"])
def test_split_render_equals_the_whole(random_scene, monkeypatch, sampler, shape):
    n, w, h = len(random_scene[0]), random_scene[6], random_scene[7]
    whole = render(random_scene, 40, sampler)
    # features fit only 32 channels at a time, an image only ~1/6 of the rays at 32 channels
    limit_buffers(monkeypatch, 4 * max(n * 32, w * h * 32 // 6))
    split = render(random_scene, 40, sampler)
    assert isinstance(split[3], list) and len(split[3]) >= 6      # it really was split
    assert torch.equal(split[0], whole[0]) and torch.equal(split[1], whole[1])
    torch.testing.assert_close(split[2], whole[2], rtol=1e-5, atol=1e-6)   # per-set sums added


def test_split_pixel_subset_and_volume_entries(random_scene, monkeypatch, shape):
    """One channel: the image rows fit but the volume selection's entries do not; the rays are halved."""
    w, h = random_scene[6], random_scene[7]
    pixels = np.stack(np.meshgrid(np.arange(0, w, 3), np.arange(0, h, 2)), -1).reshape(-1, 2)
    whole, whole_sub = render(random_scene, 1, "volume"), render(random_scene, 1, "volume", pixels=pixels)
    entries = int(whole[3].count.get()[:w * h].sum())
    limit_buffers(monkeypatch, max(4 * w * h, 4 * entries // 3))
    split, split_sub = render(random_scene, 1, "volume"), render(random_scene, 1, "volume", pixels=pixels)
    assert isinstance(split[3], list) and len(split[3]) >= 3
    assert torch.equal(split[0], whole[0]) and torch.equal(split_sub[0], whole_sub[0])
    assert torch.equal(split[1], whole[1]) and torch.equal(split_sub[1], whole_sub[1])


def test_what_cannot_be_split_is_refused_with_sizes(random_scene, monkeypatch):
    m, q, s, o, v, K, w, h = random_scene
    limit_buffers(monkeypatch, 4 * len(m) * 8)       # not even 16 channels of the features fit
    with pytest.raises(BufferLimitError, match=r"16 channels .*MiB in one device buffer.*allows .*MAX_MEM_ALLOC"):
        qr_cl.rasterize(m, q, s, o, np.ones((len(m), 20), np.float32), v, K, w, h)
    limit_buffers(monkeypatch, 4 * w * h * 4)        # a 16-channel fused image does not fit
    with pytest.raises(BufferLimitError, match=r"fused V-Render image .*rasterize"):
        qr_cl.render_volume_fused(m, q, s, o, np.ones((len(m), 16), np.float32), v, K, w, h)


def test_both_public_calls_split_the_same_way(random_scene, monkeypatch, shape):
    """rasterize and rasterization run one engine: a render too large for one buffer comes out
    the same through either, with the same gradients w.r.t. the Gaussians."""
    m, q, s, o, v, K, w, h = random_scene
    colours = np.random.default_rng(5).random((len(m), 20)).astype(np.float32)
    sets = []

    def both():
        out = []
        for call in ("rasterize", "rasterization"):
            params = [torch.from_numpy(a).requires_grad_(True) for a in (m, q, s, o, colours)]
            if call == "rasterize":
                img, _, meta = qr_cl.rasterize(*params, v, K, w, h, sampler="quantile", k=6)
                sets.append(len(meta["selection"]) if isinstance(meta["selection"], list) else 1)
            else:
                img, _, _ = qr_cl.rasterization(*params, torch.from_numpy(v)[None], torch.from_numpy(K)[None], w, h,
                                                sampler="quantile", k=6)
                img = img[0]
            img.square().sum().backward()
            out.append((img.detach(), [p.grad for p in params]))
        return out
    whole = both()
    limit_buffers(monkeypatch, 4 * max(len(m) * 16, w * h * 32 // 5))
    split = both()
    assert sets[0] == 1 and sets[1] > 1                    # the second render was split
    for (img, grads), (img_whole, grads_whole) in zip(split, whole):
        assert torch.equal(img, split[0][0]) and torch.equal(img, img_whole)
        for g, g_whole in zip(grads, grads_whole):
            torch.testing.assert_close(g, g_whole, rtol=1e-4, atol=1e-6 * float(g_whole.abs().max()))


def test_a_render_beyond_the_available_host_memory_is_refused_by_name(random_scene, monkeypatch):
    """Large host allocations are checked against MemAvailable before they are made: a render
    whose image cannot be held gets a HostMemoryError naming the sizes, not an OOM kill."""
    from qr_cl.runtime import HostMemoryError, host_pool, memory
    monkeypatch.setattr(memory, "HOST_CHECK_BYTES", 1 << 16)        # the test's image is small
    monkeypatch.setattr(memory, "available_host_bytes", lambda: 100_000)
    host_pool().clear()
    m, q, s, o, v, K, w, h = random_scene
    feats = np.random.default_rng(0).normal(size=(len(m), 64)).astype(np.float32)
    with pytest.raises(HostMemoryError) as err:
        qr_cl.rasterize(m, q, s, o, feats, v, K, w, h, sampler="quantile", k=6)
    message = str(err.value)
    assert f"({w * h}, 64) float32" in message and "GB of host memory" in message and "0.00 GB available" in message
    monkeypatch.setattr(memory, "available_host_bytes", lambda: None)   # a system that does not say
    qr_cl.rasterize(m, q, s, o, feats, v, K, w, h, sampler="quantile", k=6)


def test_available_host_memory_is_read_from_the_system():
    from qr_cl.runtime import memory
    available = memory.available_host_bytes()
    assert available is None or 0 < available < 1 << 50
