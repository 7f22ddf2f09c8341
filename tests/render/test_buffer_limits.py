"""Renders larger than the device's largest buffer: split into sets of rays (the same image) and
feature tables into row parts, read in place (the same image to float rounding), or refused with a
message naming the sizes and the limit."""
import numpy as np
import pytest
import torch

import pyopencl as cl

import qr_cl
from qr_cl.render import rays
from qr_cl.runtime import BufferLimitError, Runtime, memory, row_parts, runtime
from tests.conftest import make_random_scene

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
    # two thirds of the feature table fit at a time (two row parts), an image only ~1/8 of the rays
    limit_buffers(monkeypatch, 4 * max(n * 32, w * h * 48 // 8))
    split = render(random_scene, 40, sampler)
    assert isinstance(split[3], list) and len(split[3]) >= 8      # it really was split
    torch.testing.assert_close(split[0], whole[0], rtol=1e-5, atol=1e-6)   # the parts' blends added
    assert torch.equal(split[1], whole[1])
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
    limit_buffers(monkeypatch, 1000)                 # not one row of the features fits
    with pytest.raises(BufferLimitError, match=r"a row of 512 channels \(float32\) needs .*MiB in one device "
                                               r"buffer.*allows .*MAX_MEM_ALLOC"):
        row_parts(runtime(), 10, 512)
    limit_buffers(monkeypatch, 4 * w * h * 4)        # a 16-channel fused image does not fit
    with pytest.raises(BufferLimitError, match=r"fused V-Render image .*rasterize"):
        qr_cl.render_volume_fused(m, q, s, o, np.ones((len(m), 16), np.float32), v, K, w, h)


def test_both_public_calls_split_the_same_way(random_scene, monkeypatch, shape):
    """rasterize and rasterization run one engine: a render too large for one buffer comes out
    the same through either, with the same gradients w.r.t. the Gaussians."""
    m, q, s, o, v, K, w, h = random_scene
    colors = np.random.default_rng(5).random((len(m), 20)).astype(np.float32)
    sets = []

    def both():
        out = []
        for call in ("rasterize", "rasterization"):
            params = [torch.from_numpy(a).requires_grad_(True) for a in (m, q, s, o, colors)]
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
    from qr_cl.runtime import HostMemoryError, host_memory, host_pool
    monkeypatch.setattr(host_memory, "HOST_CHECK_BYTES", 1 << 16)   # the test's image is small
    monkeypatch.setattr(host_memory, "available_host_bytes", lambda: 100_000)
    host_pool().clear()
    m, q, s, o, v, K, w, h = random_scene
    feats = np.random.default_rng(0).normal(size=(len(m), 64)).astype(np.float32)
    with pytest.raises(HostMemoryError) as err:
        qr_cl.rasterize(m, q, s, o, feats, v, K, w, h, sampler="quantile", k=6)
    message = str(err.value)
    assert f"({w * h}, 64) float32" in message and "GB of host memory" in message and "0.00 GB available" in message
    monkeypatch.setattr(host_memory, "available_host_bytes", lambda: None)   # a system that does not say
    qr_cl.rasterize(m, q, s, o, feats, v, K, w, h, sampler="quantile", k=6)


def test_available_host_memory_is_read_from_the_system():
    from qr_cl.runtime import host_memory
    available = host_memory.available_host_bytes()
    assert available is None or 0 < available < 1 << 50


#: A scene whose feature table is larger than a selection of PIXELS rays, so that a limit a third
#: of the table splits the table alone (each part a contiguous row range of it) and not the rays.
PART_SCENE, PIXELS, PART_CHANNELS = dict(n=3000, seed=4), 100, 128


def part_render(scene, f: torch.Tensor, sampler: str, background: torch.Tensor | None, pixels: np.ndarray):
    """(image, alpha, [grads of means, quats, scales, opacities, features f, background], selection)."""
    m, q, s, o, v, K, w, h = scene
    params = [torch.from_numpy(a).requires_grad_(True) for a in (m, q, s, o)]
    bg = None if background is None else background.clone().requires_grad_(True)
    img, alpha, meta = qr_cl.rasterize(*params, f, v, K, w, h, sampler=sampler, k=6, pixels=pixels, background=bg)
    ((img * torch.linspace(-1, 1, img.numel()).reshape(img.shape)).sum() + alpha.sum()).backward()
    return img.detach(), alpha.detach(), [p.grad for p in params] + [f.grad, None if bg is None else bg.grad], \
        meta["selection"]


@pytest.mark.parametrize("sampler", ["volume", "quantile", "topk", "stratified"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_a_table_in_row_parts_renders_and_differentiates_as_the_whole(monkeypatch, sampler, dtype, shape):
    """A feature table over the buffer limit, the rays within it: the table is taken in row
    parts, each read in place (the buffers the kernels read are the table's own rows, no copy);
    the image equals the whole table's to float rounding (the parts' blends are added), alpha
    exactly, the feature gradient byte for byte (each part's rows of dF; float16 tables' in float32
    rows, split by their own size), the background's exactly, the Gaussians' to rounding (dL/dw of
    every part summed before the alphas' backward)."""
    scene = make_random_scene(**PART_SCENE)
    n, w, h = len(scene[0]), scene[6], scene[7]
    rng = np.random.default_rng(1)
    pixels = rng.integers(0, (w, h), (PIXELS, 2))
    table = torch.from_numpy(rng.normal(size=(n, PART_CHANNELS)).astype(np.float32)).to(dtype)
    for background in (None, torch.linspace(-1, 1, PART_CHANNELS)):
        whole = part_render(scene, table.clone().requires_grad_(True), sampler, background, pixels)
        f = table.clone().requires_grad_(True)
        read, parts, shared = [], [], memory.shared_array
        def spy(rt, host, access="rw"):
            if access == "r" and np.shares_memory(host, f.detach().numpy()):
                read.append(host.__array_interface__["data"][0] - f.data_ptr())
            return shared(rt, host, access)
        counted = lambda *a, **k: parts.append(row_parts(*a, **k)) or parts[-1]
        with monkeypatch.context() as patch:
            limit_buffers(patch, table.element_size() * n * PART_CHANNELS // 3 + 64)
            patch.setattr(memory, "shared_array", spy)
            patch.setattr(memory, "row_parts", counted)                  # the table's parts (table_parts)
            patch.setattr(rays, "row_parts", counted)                    # dF's
            split = part_render(scene, f, sampler, background, pixels)
        assert not isinstance(split[3], list)                        # the rays were not split
        row_bytes = table.element_size() * PART_CHANNELS
        assert [len(p) for p in parts[:1]] == [3] and max(len(p) for p in parts) == 3 * 4 // table.element_size()
        assert sorted(set(read)) == [r0 * row_bytes for r0, _ in parts[0]]   # the table's rows, in place
        torch.testing.assert_close(split[0], whole[0], rtol=1e-5, atol=1e-6 * float(whole[0].abs().max()))
        assert torch.equal(split[1], whole[1])
        names = ["means", "quats", "scales", "opacities", "features", "background"]
        for name, got, want in zip(names, split[2], whole[2]):
            if want is None:
                assert got is None
            elif name in ("features", "background"):
                assert torch.equal(got, want), name
            else:
                torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5 * float(want.abs().max()), msg=name)


def test_gsplat_absgrad_of_a_table_in_row_parts(monkeypatch):
    """gsplat's absgrad sums |dL/dmean2d| per pixel: a table in row parts gives the whole table's
    (the parts' dL/dw are summed before the per-pixel terms, which are not linear in the table)."""
    m, q, s, o, v, K, w, h = make_random_scene(**PART_SCENE)
    colors = np.random.default_rng(2).random((len(m), PART_CHANNELS)).astype(np.float32)
    out = []
    for limited in (False, True):
        if limited:
            limit_buffers(monkeypatch, 4 * len(m) * PART_CHANNELS // 3 + 64)
        params = [torch.from_numpy(a).requires_grad_(True) for a in (m, q, s, o, colors)]
        image, _, meta = qr_cl.rasterization(*params, torch.from_numpy(v)[None], torch.from_numpy(K)[None], 16, 12,
                                             sampler="quantile", k=6, absgrad=True)
        meta["means2d"].retain_grad()
        image.square().sum().backward()
        out.append(meta["means2d"].absgrad)
    torch.testing.assert_close(out[1], out[0], rtol=1e-4, atol=1e-6 * float(out[0].abs().max()))
    assert float(out[0].abs().max()) > 0


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16])
def test_fused_volume_render_of_a_table_in_row_parts(monkeypatch, dtype):
    """The fused V-Render walks the tile lists once per row part: the image of the parts added, the
    whole table's to float rounding; alpha and depth exactly."""
    m, q, s, o, v, K, w, h = make_random_scene(n=3000, seed=4, width=24, height=16)   # image < table / 3
    table = torch.from_numpy(np.random.default_rng(3).normal(size=(len(m), PART_CHANNELS)).astype(np.float32)).to(dtype)
    bg = np.linspace(-1, 1, PART_CHANNELS)
    whole = qr_cl.render_volume_fused(m, q, s, o, table, v, K, w, h, background=bg)
    limit_buffers(monkeypatch, table.element_size() * len(m) * PART_CHANNELS // 3 + 64)
    parts = row_parts(runtime(), len(m), PART_CHANNELS, table.element_size())
    split = qr_cl.render_volume_fused(m, q, s, o, table, v, K, w, h, background=bg)
    assert len(parts) == 3
    torch.testing.assert_close(split[0], whole[0], rtol=1e-5, atol=1e-6 * float(whole[0].abs().max()))
    assert torch.equal(split[1], whole[1]) and np.array_equal(split[2]["depth"], whole[2]["depth"])
