"""torch autograd through rasterize(): gradients w.r.t. features equal torch's on the reference."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.render import blend, rasterize_plan
from qr_cl.stages import select, select_ref


def torch_reference(h: dict, features: torch.Tensor, background=None) -> torch.Tensor:
    """image [P,C] = sum_j w F[id] (+ t_rem bg) in torch, from a reference selection."""
    ids = torch.from_numpy(h["ids"].astype(np.int64))
    w = torch.from_numpy(h["weights"]).to(features.dtype) * (ids >= 0)
    image = (w[..., None] * features[ids.clamp(min=0)]).sum(1)
    if background is not None:
        image = image + torch.from_numpy(h["t_rem"]).to(features.dtype)[:, None] * background[None]
    return image


@pytest.mark.parametrize("sampler,k", [("quantile", 5), ("topk", 5), ("volume", 1), ("stratified", 5)])
@pytest.mark.parametrize("with_pixels", [False, True])
def test_gradients_equal_reference(random_scene, sampler, k, with_pixels):
    m, q, s, o, v, K, w, h = random_scene
    torch.manual_seed(0)
    features = torch.randn(len(m), 24, requires_grad=True)
    background = torch.randn(24, requires_grad=True)
    pixels = np.random.default_rng(1).integers(0, [w, h], (300, 2)) if with_pixels else None
    render, _, meta = qr_cl.rasterize(m, q, s, o, features, v, K, w, h, sampler=sampler, k=k,
                                      background=background, pixels=pixels)
    target = torch.randn(render.shape)
    (render * target).sum().backward()

    plan_meta = meta
    rays = pixels if with_pixels else np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2)
    h_ref = select_ref.select(plan_meta, plan_meta["tile_ranges"], meta["selection"].plan.ids.get(), rays, w, sampler, k)
    f_ref = features.detach().clone().requires_grad_(True)
    b_ref = background.detach().clone().requires_grad_(True)
    want = torch_reference(h_ref, f_ref, b_ref)
    (want * target.reshape(want.shape)).sum().backward()
    scale = f_ref.grad.abs().max()
    torch.testing.assert_close(render.reshape(want.shape), want.detach(), rtol=1e-5, atol=1e-5 * float(want.detach().abs().max()))
    torch.testing.assert_close(features.grad, f_ref.grad, rtol=1e-5, atol=1e-5 * float(scale))
    torch.testing.assert_close(background.grad, b_ref.grad, rtol=1e-5, atol=1e-5 * float(b_ref.grad.abs().max()))


def test_gradcheck_tiny(random_scene):
    plan = rasterize_plan(*random_scene)
    sel = select(plan, "quantile", 3, np.array([[10, 20], [20, 25], [33, 10], [69, 49]]))
    features = torch.randn(sel.n_gaussians, 3, dtype=torch.float64, requires_grad=True)
    # The device computes in float32; the blend is linear, so a large step is exact.
    assert torch.autograd.gradcheck(lambda f: blend(sel, f), (features,), eps=1e-1, atol=1e-4, rtol=1e-4)


def test_backward_twice_identical_bytes(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    features = torch.randn(len(m), 64, requires_grad=True)
    render, _, meta = qr_cl.rasterize(m, q, s, o, features, v, K, w, h, sampler="quantile", k=10)
    grad = torch.randn(render.shape)
    first = torch.autograd.grad(render, features, grad, retain_graph=True)[0]
    second = torch.autograd.grad(render, features, grad)[0]       # over the transpose or bounds the first made
    assert first.numpy().tobytes() == second.numpy().tobytes()


def test_rasterize_and_rasterization_share_the_engine(random_scene):
    """Both public calls render through one engine: the same image and the same gradients w.r.t.
    features and Gaussians for the same inputs (rasterization normalises quats, here unit)."""
    m, q, s, o, v, K, w, h = random_scene
    features = torch.randn(len(m), 4)
    inputs = [[torch.from_numpy(a).requires_grad_(True) for a in (m, q, s, o)] + [features.clone().requires_grad_(True)]
              for _ in range(2)]
    a, _, _ = qr_cl.rasterize(*inputs[0], v, K, w, h, sampler="topk", k=3)
    b, _, _ = qr_cl.rasterization(*inputs[1][:4], inputs[1][4], torch.from_numpy(v)[None], torch.from_numpy(K)[None],
                                  w, h, sampler="topk", k=3)
    weights = torch.randn(h, w, 4)
    (a * weights).sum().backward()
    (b[0] * weights).sum().backward()
    torch.testing.assert_close(a, b[0], rtol=1e-6, atol=1e-6)
    for name, x, y in zip(("means", "quats", "scales", "opacities", "features"), *inputs):
        assert x.grad is not None and x.grad.abs().sum() > 0, name
        torch.testing.assert_close(x.grad, y.grad, rtol=1e-5, atol=1e-6 * float(y.grad.abs().max()), msg=name)


def test_fused_volume_without_grad_matches_selection_path(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    features = torch.randn(len(m), 8)
    fused, alpha_f, meta_f = qr_cl.render_volume_fused(m, q, s, o, features, v, K, w, h)
    graded, alpha_g, meta_g = qr_cl.rasterize(m, q, s, o, features.requires_grad_(True), v, K, w, h)
    assert "depth" in meta_f and "selection" in meta_g
    torch.testing.assert_close(graded.detach(), fused, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(alpha_g, alpha_f, rtol=1e-6, atol=1e-6)
