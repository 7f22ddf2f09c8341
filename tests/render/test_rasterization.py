"""qr_cl.rasterization: gsplat's interface, the same images as rasterize, and gradients w.r.t. the
Gaussians equal to the torch twins' (project_ref.ewa -> blend_ref.render_rays), which pass
gradcheck in float64."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.stages import blend_ref, project_ref, sh_ref
from qr_cl.runtime import SPLAT, SPLAT_FLOATS

SAMPLERS_K = [("volume", 40), ("quantile", 5), ("topk", 4), ("stratified", 4)]


def tensors(*arrays, grad: bool = False) -> list[torch.Tensor]:
    return [torch.tensor(np.asarray(a, np.float32), requires_grad=grad) for a in arrays]


def turned_cameras(viewmat: np.ndarray, K: np.ndarray, angles=(0.0, 0.05)) -> tuple[torch.Tensor, torch.Tensor]:
    """viewmats [C,4,4]: the given camera turned by each angle (rad) about y and shifted sideways
    by twice it, and Ks [C,3,3]."""
    views = [np.array([[np.cos(a), 0, np.sin(a), 2 * a], [0, 1, 0, 0], [-np.sin(a), 0, np.cos(a), 0],
                       [0, 0, 0, 1]]) @ viewmat for a in angles]
    return torch.tensor(np.stack(views), dtype=torch.float32), torch.tensor(np.stack([K] * len(angles)))


def twin_render(means, quats, scales, opacities, colors, viewmat, K, width, height, selection, background=None):
    """The float64 torch twin of one camera's render through the kernel's selection (its rays'
    Gaussian lists): image [H*W, C] and alpha [H*W] (1 - final T)."""
    e = project_ref.ewa(means, quats / quats.norm(dim=-1, keepdim=True), scales, viewmat, K, width, height)
    ys, xs = np.mgrid[0:height, 0:width]
    pixels = np.stack([xs.ravel(), ys.ravel()], 1)
    image, t_final = blend_ref.render_rays(e["means2d"], e["conics"], opacities.double(), colors.double(),
                                           selection.host()["ids"], pixels, selection.sampler != "volume",
                                           None if background is None else background.double())
    return image, 1 - t_final


@pytest.mark.parametrize("sampler,k", SAMPLERS_K)
def test_same_images_as_rasterize(random_scene, sampler, k):
    m, q, s, o, v, K, w, h = random_scene
    colors = np.random.default_rng(0).random((len(m), 5)).astype(np.float32)
    viewmats, Ks = turned_cameras(v, K)
    image, alpha, meta = qr_cl.rasterization(*tensors(m, q, s, o, colors), viewmats, Ks, w, h, sampler=sampler, k=k,
                                             packed=False)
    assert image.shape == (2, h, w, 5) and alpha.shape == (2, h, w, 1)
    assert meta["radii"].shape == (2, len(m), 2) and meta["radii"].dtype == torch.int32
    for c in range(2):
        want, want_alpha, want_meta = qr_cl.rasterize(m, q, s, o, colors, viewmats[c].numpy(), K, w, h,
                                                      sampler=sampler, k=k)
        torch.testing.assert_close(image[c], want, atol=2e-6, rtol=1e-5)
        torch.testing.assert_close(alpha[c], want_alpha, atol=2e-6, rtol=1e-5)
        np.testing.assert_array_equal(meta["radii"][c].numpy(), want_meta["radii"])
        np.testing.assert_allclose(meta["means2d"][c].numpy(), want_meta["means2d"], atol=1e-3)
    assert meta["tile_width"] * meta["tile_size"] >= w and meta["isect_offsets"].shape == (2, meta["tile_height"],
                                                                                         meta["tile_width"])


def real_scene(gaussians, camera, width: int = 64) -> tuple:
    """(means, quats, scales, opacities, viewmat, K, width, height) of a real scene and a camera
    scaled to ``width`` px."""
    f = width / camera.width
    K = (camera.K * np.array([[f], [f], [1]])).astype(np.float32)
    g = gaussians
    return g.means, g.quats, g.scales, g.opacities, camera.viewmat, K, width, int(round(camera.height * f))


@pytest.fixture(params=["random", "fox", "donut"])
def scene(request, random_scene):
    """The random scene, and (when ../shared/data exists) the fox and the donut at 64 px wide."""
    if request.param == "random":
        return random_scene
    if request.param == "fox":
        fox = request.getfixturevalue("fox")
        return real_scene(fox, qr_cl.orbit_cameras(fox.means, 4)[1])
    donut, cameras = request.getfixturevalue("donut")
    return real_scene(donut, cameras[0])


@pytest.mark.parametrize("sampler,k", SAMPLERS_K)
def test_gradients_equal_twin(scene, sampler, k):
    m, q, s, o, v, K, w, h = scene
    rng = np.random.default_rng(1)
    colors = rng.random((len(m), 3)).astype(np.float32)
    inputs = tensors(m, 1.7 * q, s, o, colors, rng.random(3), grad=True)     # quats need not be unit
    image, alpha, meta = qr_cl.rasterization(*inputs[:5], torch.tensor(v)[None], torch.tensor(K)[None], w, h,
                                             backgrounds=inputs[5][None], sampler=sampler, k=k)
    target, target_alpha = torch.randn(image.shape), torch.randn(alpha.shape)
    loss = (image * target).sum() + ((alpha * target_alpha).sum() if sampler == "volume" else 0)
    loss.backward()

    twin_inputs = [t.detach().double().requires_grad_(True) for t in inputs]
    twin_image, twin_alpha = twin_render(*twin_inputs[:5], v, K, w, h, meta["selections"][0], twin_inputs[5])
    twin_loss = (twin_image * target.double().reshape(twin_image.shape)).sum()
    if sampler == "volume":
        twin_loss = twin_loss + (twin_alpha * target_alpha.double().reshape(-1)).sum()
    twin_loss.backward()
    torch.testing.assert_close(image.reshape(twin_image.shape).double(), twin_image.detach(), atol=1e-5, rtol=1e-4)
    for name, got, twin in zip(["means", "quats", "scales", "opacities", "colors", "backgrounds"], inputs, twin_inputs):
        scale = float(twin.grad.abs().max())
        assert scale > 0, name
        torch.testing.assert_close(got.grad.double(), twin.grad, atol=2e-4 * scale, rtol=1e-3, msg=name)


def test_backward_is_bitwise_deterministic(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    colors = np.random.default_rng(2).random((len(m), 8)).astype(np.float32)
    target = torch.randn(1, h, w, 8)
    runs = []
    for _ in range(2):
        inputs = tensors(m, q, s, o, colors, grad=True)
        image, _, _ = qr_cl.rasterization(*inputs, torch.tensor(v)[None], torch.tensor(K)[None], w, h,
                                          sampler="quantile", k=6)
        (image * target).sum().backward()
        runs.append([t.grad.numpy().tobytes() for t in inputs])
    assert runs[0] == runs[1]


def test_render_modes(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    colors = np.random.default_rng(3).random((len(m), 3)).astype(np.float32)
    args = (*tensors(m, q, s, o, colors), torch.tensor(v)[None], torch.tensor(K)[None], w, h)
    rgb, alpha, _ = qr_cl.rasterization(*args, backgrounds=torch.ones(1, 3))
    rgbd, _, _ = qr_cl.rasterization(*args, render_mode="RGB+D", backgrounds=torch.ones(1, 3))
    d, _, _ = qr_cl.rasterization(*args, render_mode="D")
    ed, _, _ = qr_cl.rasterization(*args, render_mode="ED")
    depth = torch.tensor(m @ v[2, :3] + v[2, 3])[:, None]
    want_d, _, _ = qr_cl.rasterize(m, q, s, o, depth, v, K, w, h)
    assert rgbd.shape == (1, h, w, 4) and d.shape == ed.shape == (1, h, w, 1)
    torch.testing.assert_close(rgbd[..., :3], rgb)                    # depth's background is 0 ...
    torch.testing.assert_close(rgbd[..., 3:], d)
    torch.testing.assert_close(d[0], want_d, atol=1e-5, rtol=1e-5)    # ... and D = sum_i w_i z_i
    torch.testing.assert_close(ed, d / alpha.clamp_min(1e-10))
    hit = alpha[..., 0] > 0.5
    assert (ed[hit] >= depth.min() - 1e-3).all() and (ed[hit] <= depth.max() + 1e-3).all()


@pytest.mark.parametrize("option,value", [("rasterize_mode", "antialiased"), ("eps2d", 0.1), ("tile_size", 8),
                                          ("camera_model", "fisheye"), ("radial_coeffs", torch.zeros(1, 6)),
                                          ("covars", torch.zeros(1, 3, 3))])
def test_unsupported_gsplat_options_raise(random_scene, option, value):
    m, q, s, o, v, K, w, h = random_scene
    with pytest.raises(ValueError, match=option):
        qr_cl.rasterization(*tensors(m, q, s, o, np.ones((len(m), 3))), torch.tensor(v)[None],
                            torch.tensor(K)[None], w, h, **{option: value})


def test_bad_shapes_and_modes_raise(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    args = tensors(m, q, s, o, np.ones((len(m), 3)))
    with pytest.raises(ValueError, match="viewmats"):
        qr_cl.rasterization(*args, torch.tensor(v), torch.tensor(K), w, h)
    with pytest.raises(ValueError, match="render_mode"):
        qr_cl.rasterization(*args, torch.tensor(v)[None], torch.tensor(K)[None], w, h, render_mode="N")
    with pytest.raises(ValueError, match="Ks"):
        qr_cl.rasterization(*args, torch.tensor(v)[None], torch.tensor(K, requires_grad=True)[None], w, h)
    with pytest.raises(ValueError, match="sh_degree"):
        qr_cl.rasterization(*args, torch.tensor(v)[None], torch.tensor(K)[None], w, h, sh_degree=1)


def test_sh_colors_and_their_gradients(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    sh = np.random.default_rng(4).normal(0, 0.3, (len(m), 9, 3)).astype(np.float32)
    inputs = tensors(m, q, s, o, sh, grad=True)
    image, _, _ = qr_cl.rasterization(*inputs, torch.tensor(v)[None], torch.tensor(K)[None], w, h, sh_degree=2)
    want, _, _ = qr_cl.rasterize(m, q, s, o, sh, v, K, w, h, sh_degree=2)
    torch.testing.assert_close(image[0], want, atol=1e-5, rtol=1e-4)
    image.sum().backward()
    assert inputs[4].grad.abs().sum() > 0 and inputs[4].grad[:, 9:].abs().sum() == 0


def test_twins_pass_gradcheck():
    rng = np.random.default_rng(5)
    n = 4
    means = torch.tensor(np.c_[rng.uniform(-1, 1, (n, 2)), rng.uniform(2, 4, n)], requires_grad=True)
    quats = torch.tensor(rng.standard_normal((n, 4)), requires_grad=True)
    scales = torch.tensor(rng.uniform(0.1, 0.5, (n, 3)), requires_grad=True)
    view = np.eye(4)
    view[:3, 3] = [0.1, -0.2, 0.3]
    K = np.array([[40.0, 0, 16], [0, 40, 12], [0, 0, 1]])
    assert torch.autograd.gradcheck(lambda *a: project_ref.ewa(*a, view, K, 32, 24)["conics"],
                                    (means, quats, scales))
    assert torch.autograd.gradcheck(lambda *a: project_ref.ewa(*a, view, K, 32, 24)["means2d"],
                                    (means, quats, scales))
    means2d = torch.tensor(rng.uniform(0, 8, (n, 2)), requires_grad=True)
    conics = torch.tensor(np.c_[rng.uniform(0.2, 0.5, n), rng.uniform(-0.05, 0.05, n), rng.uniform(0.2, 0.5, n)],
                          requires_grad=True)
    opacities = torch.tensor(rng.uniform(0.1, 0.9, n), requires_grad=True)
    features = torch.tensor(rng.standard_normal((n, 2)), requires_grad=True)
    ids = np.array([[0, 1, 2, 3], [2, 0, -1, -1], [3, -1, -1, -1]])
    pixels = rng.integers(0, 8, (3, 2))
    for normalized in (False, True):
        assert torch.autograd.gradcheck(lambda *a: blend_ref.render_rays(*a, ids, pixels, normalized),
                                        (means2d, conics, opacities, features))
    sh = torch.tensor(rng.standard_normal((n, 16, 3)) * 0.2, requires_grad=True)
    assert torch.autograd.gradcheck(lambda mm, c: sh_ref.sh_to_rgb(mm, c, torch.zeros(3, dtype=torch.float64)),
                                    (means, sh))


def test_fit_a_small_scene(random_scene):
    """Optimising perturbed Gaussians against three views of the true ones: loss falls, PSNR rises."""
    m, q, s, o, v, K, w, h = random_scene
    rng = np.random.default_rng(6)
    colors = rng.random((len(m), 3)).astype(np.float32)
    viewmats, Ks = turned_cameras(v, K, (-0.05, 0.0, 0.05))
    with torch.no_grad():
        target, _, _ = qr_cl.rasterization(*tensors(m, q, s, o, colors), viewmats, Ks, w, h)
    means = torch.tensor(m + rng.normal(0, 0.03, m.shape).astype(np.float32), requires_grad=True)
    log_scales = torch.tensor(np.log(s), requires_grad=True)
    logit_op = torch.tensor(np.log(np.clip(o, 0.05, 0.95) / (1 - np.clip(o, 0.05, 0.95))), requires_grad=True)
    quats = torch.tensor(q, requires_grad=True)
    rgb = torch.tensor(rng.random((len(m), 3)).astype(np.float32), requires_grad=True)
    opt = torch.optim.Adam([means, log_scales, logit_op, quats, rgb], lr=0.01)
    losses = []
    for _ in range(40):
        image, _, _ = qr_cl.rasterization(means, quats, log_scales.exp(), torch.sigmoid(logit_op), rgb,
                                          viewmats, Ks, w, h)
        loss = ((image - target) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    psnr = [10 * np.log10(1 / x) for x in (losses[0], losses[-1])]
    assert losses[-1] < 0.3 * losses[0] and psnr[1] > psnr[0] + 5, (losses[0], losses[-1])


def test_per_camera_colors_and_no_gaussians(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    colors = np.random.default_rng(7).random((2, len(m), 4)).astype(np.float32)
    viewmats, Ks = turned_cameras(v, K)
    image, _, _ = qr_cl.rasterization(*tensors(m, q, s, o), torch.from_numpy(colors), viewmats, Ks, w, h)
    for c in range(2):
        single, _, _ = qr_cl.rasterization(*tensors(m, q, s, o, colors[c]), viewmats[c:c + 1], Ks[c:c + 1], w, h)
        torch.testing.assert_close(image[c], single[0])
    bg = torch.tensor([[0.2, 0.4, 0.6, 0.8]] * 2)
    empty = [torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0)]
    for packed in (False, True):
        image, alpha, meta = qr_cl.rasterization(*empty, torch.zeros(0, 4), viewmats, Ks, w, h, backgrounds=bg,
                                                 render_mode="RGB+D", packed=packed)
        assert image.shape == (2, h, w, 5) and (image[..., :4] == bg[:, None, None]).all()
        assert (image[..., 4] == 0).all() and (alpha == 0).all()
        assert meta["radii"].shape == ((0, 2) if packed else (2, 0, 2)) and meta["flatten_ids"].shape == (0,)
    with pytest.raises(ValueError, match="quats has shape"):
        qr_cl.rasterization(*tensors(m, q[:, :3], s, o, colors[0]), viewmats, Ks, w, h)


@pytest.mark.parametrize("sampler,k", SAMPLERS_K)
@pytest.mark.parametrize("parts", [1, 3])
def test_alpha_gradients_follow_the_derivation(random_scene, sampler, k, parts):
    """weight_grads -> blend_backward_alpha (kernels) = blend_ref.alpha_grads (the written
    derivation) = torch's autograd of the weights, per selected entry; dL/dw summed from the whole
    table or from row parts of it."""
    from qr_cl.render import rasterize_plan
    from qr_cl.runtime import channel_layout, device_empty, device_rows, runtime
    from qr_cl.stages import blend_backward_alpha, select, weight_grads
    m, q, s, o, v, K, w, h = random_scene
    rng = np.random.default_rng(8)
    features = rng.standard_normal((len(m), 6)).astype(np.float32)
    pixels = rng.integers(0, [w, h], (200, 2)).astype(np.int32)
    sel = select(rasterize_plan(m, q, s, o, v, K, w, h), sampler, k, pixels)
    dimage = rng.standard_normal((sel.n_rays, 6)).astype(np.float32)
    d_trem = rng.standard_normal(sel.n_rays).astype(np.float32) if sampler == "volume" else None
    cstride = channel_layout(6)[2]
    cuts = np.linspace(0, len(m), parts + 1).astype(int)
    d_w = device_empty(runtime(), sel.ids.shape)
    with device_rows(runtime(), dimage, cstride) as d:
        for r0, r1 in zip(cuts[:-1], cuts[1:]):
            with device_rows(runtime(), features[r0:r1], cstride) as f:
                weight_grads(sel, f, d, 6, row0=int(r0), out=d_w)
    kernel = blend_backward_alpha(sel, d_w, d_trem).get()
    hst = sel.host()
    ids, valid = hst["ids"], hst["ids"] >= 0
    rows = sel.offsets.get()[:sel.n_rays, None] + np.arange(ids.shape[1])[None]
    kernel = np.where(valid, kernel[np.where(valid, rows, 0)], 0)

    e = project_ref.ewa(m, q, s, v, K, w, h)
    centre = pixels[:, None] + 0.5
    dx, dy = (e["means2d"].numpy()[np.maximum(ids, 0)] - centre).transpose(2, 0, 1)
    A, B, C = e["conics"].numpy()[np.maximum(ids, 0)].transpose(2, 0, 1)
    sigma = 0.5 * (A * dx ** 2 + C * dy ** 2) + B * dx * dy
    alphas = np.where(valid, np.minimum(0.99, o[np.maximum(ids, 0)] * np.exp(-sigma)), 0)
    g = np.where(valid, np.einsum("pc,plc->pl", dimage.astype(np.float64), features[np.maximum(ids, 0)]), 0)
    derived = np.where(valid, blend_ref.alpha_grads(alphas, g, sampler != "volume", d_trem), 0)

    a = torch.tensor(alphas, requires_grad=True)
    T = torch.cumprod(torch.cat([torch.ones(len(a), 1, dtype=a.dtype), 1 - a], 1), 1)
    u = T[:, :-1] * a
    weights = u / u.sum(1, keepdim=True).clamp_min(1e-300) if sampler != "volume" else u
    loss = (weights * torch.tensor(g)).sum()
    if d_trem is not None:
        loss = loss + (T[:, -1] * torch.tensor(d_trem, dtype=a.dtype)).sum()
    loss.backward()
    auto = np.where(valid, a.grad.numpy(), 0)
    scale = np.abs(auto).max()
    np.testing.assert_allclose(derived, auto, atol=1e-9 * scale)
    np.testing.assert_allclose(kernel, auto, atol=2e-4 * scale)


@pytest.mark.parametrize("sampler,k", [("volume", 40), ("quantile", 5)])
def test_a_row_parts_geometry_gradient_equals_its_twin(random_scene, sampler, k):
    """The geometry backward of one row part of a table, the other rows' entries blending nothing
    (their dL/dw 0): weight_grads -> blend_backward_alpha -> splat_backward equals the gradient of
    the twin render_rays of that part (row0) w.r.t. means2d, conics and opacities."""
    from qr_cl.render import rasterize_plan
    from qr_cl.runtime import channel_layout, device_rows, device_zeros, runtime
    from qr_cl.stages import blend_backward_alpha, select, splat_backward, weight_grads
    m, q, s, o, v, K, w, h = random_scene
    rng = np.random.default_rng(11)
    r0, r1 = len(m) // 4, len(m) * 2 // 3
    features = rng.standard_normal((len(m), 6)).astype(np.float32)
    pixels = rng.integers(0, [w, h], (300, 2)).astype(np.int32)
    plan = rasterize_plan(m, q, s, o, v, K, w, h)
    sel = select(plan, sampler, k, pixels)
    dimage = rng.standard_normal((sel.n_rays, 6)).astype(np.float32)
    cstride = channel_layout(6)[2]
    d_w = device_zeros(runtime(), sel.ids.shape)
    with device_rows(runtime(), dimage, cstride) as d, device_rows(runtime(), features[r0:r1], cstride) as f:
        weight_grads(sel, f, d, 6, row0=r0, out=d_w)
    kernel = splat_backward(sel, blend_backward_alpha(sel, d_w)).get()
    splats = torch.from_numpy(plan.splats.get().reshape(-1, SPLAT_FLOATS).astype(np.float64))
    means2d, conics, opacities = (splats[:, c].clone().requires_grad_(True) for c in (SPLAT.mean, SPLAT.conic, SPLAT.opacity))
    image, _ = blend_ref.render_rays(means2d, conics, opacities, torch.from_numpy(features[r0:r1]).double(),
                                     sel.host()["ids"], pixels, sampler != "volume", row0=r0)
    (image * torch.from_numpy(dimage).double()).sum().backward()
    for got, twin in ((kernel[:, SPLAT.mean], means2d), (kernel[:, SPLAT.conic], conics), (kernel[:, SPLAT.opacity], opacities)):
        scale = float(twin.grad.abs().max())
        assert scale > 0
        np.testing.assert_allclose(got, twin.grad.numpy(), atol=2e-4 * scale, rtol=1e-3)


def test_pixel_subset_gradients_equal_twin(random_scene):
    """The engine on a pixel subset (View.pixels; the kernels' non-full ray path)."""
    from qr_cl.render import View, checked_runtime, render_view
    m, q, s, o, v, K, w, h = random_scene
    rng = np.random.default_rng(9)
    pixels = rng.integers(0, [w, h], (300, 2)).astype(np.int32)
    colors = rng.random((len(m), 3)).astype(np.float32)
    inputs = tensors(m, q, s, o, colors, grad=True)
    view = View(v, K, w, h, sampler="quantile", k=5, pixels=pixels)
    out = render_view(*inputs, None, view, rt=checked_runtime())
    image, sel = out.image, out.selections[0]
    target = torch.randn(image.shape)
    (image * target).sum().backward()
    twin = [t.detach().double().requires_grad_(True) for t in inputs]
    e = project_ref.ewa(twin[0], twin[1], twin[2], v, K, w, h)
    want, _ = blend_ref.render_rays(e["means2d"], e["conics"], twin[3], twin[4], sel.host()["ids"], pixels, True)
    (want * target.double()).sum().backward()
    for name, got, ref in zip(["means", "quats", "scales", "opacities", "colors"], inputs, twin):
        scale = float(ref.grad.abs().max())
        torch.testing.assert_close(got.grad.double(), ref.grad, atol=2e-4 * scale, rtol=1e-3, msg=name)
