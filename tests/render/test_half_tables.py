"""Half-precision feature tables: a float16 table is read as half and blended in float32, so its
render is bit for bit the render of the float32 table holding the same values (the twin of a
half table is the float32 path), within float16 rounding of the original float32 table's; its
gradient is that float32 gradient rounded to float16. Every path that reads a table: the K
samplers with the blend fused into the selection and apart, V-Render, the fused V-Render, pixel
subsets, both launch shapes, the geometry backward and gsplat's call."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.render.rays import table_rows
from qr_cl.runtime import row_parts, runtime

CHANNELS = 40          # padded rows (cstride 48) and more than one vector
#: The issue's tolerance: a half table's image within this fraction of the largest value.
HALF_RTOL = 2e-3


def tables(n: int, channels: int = CHANNELS, seed: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """A float32 table [n, channels] and its float16 rounding."""
    f32 = torch.from_numpy(np.random.default_rng(seed).normal(size=(n, channels)).astype(np.float32))
    return f32, f32.half()


@pytest.mark.parametrize("launch", ["cpu", "gpu"])
@pytest.mark.parametrize("sampler", ["volume", "quantile", "topk", "stratified"])
def test_a_half_table_renders_as_the_float_table_of_its_values(random_scene, monkeypatch, launch, sampler):
    m, q, s, o, v, K, w, h = random_scene
    monkeypatch.setattr(runtime(), "gpu_shaped", launch == "gpu")
    f32, f16 = tables(len(m))
    pixels = np.random.default_rng(2).integers(0, (w, h), (90, 2))
    background = torch.linspace(-1, 1, CHANNELS)
    for px in (None, pixels):
        half, alpha_h, _ = qr_cl.rasterize(m, q, s, o, f16, v, K, w, h, sampler=sampler, k=6, pixels=px,
                                           background=background)
        same, alpha_f, _ = qr_cl.rasterize(m, q, s, o, f16.float(), v, K, w, h, sampler=sampler, k=6, pixels=px,
                                           background=background)
        full, _, _ = qr_cl.rasterize(m, q, s, o, f32, v, K, w, h, sampler=sampler, k=6, pixels=px,
                                     background=background)
        assert half.dtype == torch.float32 and alpha_h.dtype == torch.float32
        assert half.numpy().tobytes() == same.numpy().tobytes() and torch.equal(alpha_h, alpha_f)
        assert float((half - full).abs().max()) <= HALF_RTOL * float(full.abs().max())
        assert float((half - full).abs().max()) > 0          # the table really was rounded


def test_a_numpy_half_table_stays_half_and_is_read_in_place(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    _, f16 = tables(len(m), 64)
    from_numpy, _, _ = qr_cl.rasterize(m, q, s, o, f16.numpy(), v, K, w, h, sampler="quantile", k=6)
    from_torch, _, _ = qr_cl.rasterize(m, q, s, o, f16, v, K, w, h, sampler="quantile", k=6)
    assert torch.equal(from_numpy, from_torch)
    rows = table_rows(f16)
    assert rows.dtype == np.float16 and np.shares_memory(rows, f16.numpy())   # no float32 copy


def test_the_gradient_of_a_half_table_is_half(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    _, f16 = tables(len(m))
    for px in (None, np.random.default_rng(3).integers(0, (w, h), (70, 2))):   # scatter, gather
        grads = {}
        for name, table in (("half", f16), ("float", f16.float())):
            x = table.clone().requires_grad_(True)
            image, _, _ = qr_cl.rasterize(m, q, s, o, x, v, K, w, h, sampler="quantile", k=6, pixels=px)
            image.square().sum().backward()
            grads[name] = x.grad
        assert grads["half"].dtype == torch.float16
        assert torch.equal(grads["half"], grads["float"].half())


@pytest.mark.parametrize("sampler", ["volume", "quantile"])
def test_geometry_gradients_read_the_half_table(random_scene, sampler):
    """gsplat's call with float16 colors: the same image and Gaussian gradients as the float32
    colors of the same values (blend_backward_alpha reads the half rows)."""
    m, q, s, o, v, K, w, h = random_scene
    _, f16 = tables(len(m), 3)
    out = {}
    for name, colors in (("half", f16), ("float", f16.float())):
        params = [torch.from_numpy(np.asarray(a, np.float32)).requires_grad_(True) for a in (m, q, s, o)]
        c = colors.clone().requires_grad_(True)
        image, _, _ = qr_cl.rasterization(*params, c, torch.from_numpy(v)[None], torch.from_numpy(K)[None], w, h,
                                          sampler=sampler, k=6)
        (image * torch.linspace(0, 1, image.numel()).reshape(image.shape)).sum().backward()
        assert c.grad.dtype == colors.dtype
        out[name] = [image.detach()] + [p.grad for p in params] + [c.grad.half()]   # rounded as a half table's
    for got, want in zip(out["half"], out["float"]):
        assert got.numpy().tobytes() == want.numpy().tobytes()


def test_fused_volume_render_of_a_half_table(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    _, f16 = tables(len(m), 512)
    half, alpha_h, _ = qr_cl.render_volume_fused(m, q, s, o, f16, v, K, w, h)
    same, alpha_f, _ = qr_cl.render_volume_fused(m, q, s, o, f16.float(), v, K, w, h)
    assert half.numpy().tobytes() == same.numpy().tobytes() and torch.equal(alpha_h, alpha_f)


def test_a_half_table_needs_half_the_buffer(random_scene, monkeypatch):
    """Row parts are sized by the table's element size: a half table that fits one buffer is read
    whole where its float32 table must be split into two row parts."""
    rt = runtime()
    n = 1000
    monkeypatch.setattr(type(rt), "max_buffer_bytes", property(lambda self: 2 * n * 512 + 1))
    assert row_parts(rt, n, 512, itemsize=2) == [(0, n)]
    assert row_parts(rt, n, 512) == [(0, 500), (500, n)]


def test_a_half_table_wanting_a_gradient_is_split_for_its_float32_gradient(random_scene, monkeypatch):
    """A half table that fits one buffer while its float32 gradient does not is read whole and its
    gradient summed in row parts that fit: the same image, and the gradient within float16
    rounding (the limit also splits the rays, and autograd adds the sets' gradients in float16)."""
    from tests.render.test_buffer_limits import limit_buffers
    m, q, s, o, v, K, w, h = random_scene
    _, f16 = tables(len(m), 64)
    out = []
    for limited in (False, True):
        if limited:
            limit_buffers(monkeypatch, 2 * len(m) * 64 + 64)       # the half table, not float32 dF
        x = f16.clone().requires_grad_(True)
        image, _, _ = qr_cl.rasterize(m, q, s, o, x, v, K, w, h, sampler="quantile", k=6)
        image.square().sum().backward()
        out.append((image.detach(), x.grad))
    assert torch.equal(out[0][0], out[1][0])
    grads = [g.float() for _, g in out]
    assert float((grads[0] - grads[1]).abs().max()) <= HALF_RTOL * float(grads[0].abs().max())
