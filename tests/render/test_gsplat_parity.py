"""gsplat parity of qr_cl.rasterization (issue 29): gradients w.r.t. gsplat's 2-D meta tensors
(means2d, conics, opacities) and AbsGS's absgrad against the float64 twins, packed and dense meta,
gsplat's tile-intersection layout, radii [C,N,2], gradients w.r.t. viewmats against the twins and
finite differences, both launch shapes, extra signals through the colors' selection, and
densification: gsplat's own DefaultStrategy (when gsplat is installed) and the example's."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.stages import blend_ref, project_ref, sh_ref
from tests.render.test_rasterization import SAMPLERS_K, tensors, turned_cameras


def all_pixels(width: int, height: int) -> np.ndarray:
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs.ravel(), ys.ravel()], 1)


def render(scene, colors, sampler="volume", k=40, packed=False, absgrad=False, viewmats=None, seed=0, **kw):
    """rasterization of two cameras with every input requiring grad, the 2-D meta tensors'
    gradients retained; loss = sum(image * a seeded target). Returns (inputs, image, meta, target)."""
    m, q, s, o, v, K, w, h = scene
    views, Ks = turned_cameras(v, K) if viewmats is None else (viewmats, torch.tensor(np.stack([K] * len(viewmats))))
    inputs = tensors(m, q, s, o, colors, grad=True)
    image, alpha, meta = qr_cl.rasterization(*inputs, views, Ks, w, h, sampler=sampler, k=k, packed=packed,
                                             absgrad=absgrad, **kw)
    for key in ("means2d", "conics", "opacities", "depths"):
        meta[key].retain_grad()
    target = torch.randn(image.shape, generator=torch.Generator().manual_seed(seed))
    (image * target).sum().backward()
    return inputs, image, meta, target


def twin_splat_grads(meta, c: int, colors: np.ndarray, target: torch.Tensor, opacities: np.ndarray):
    """The float64 twin (blend_ref.render_rays through the kernel's selection of camera c, at the
    kernel's own splats) of dL/dmeans2d [N,2], its absgrad (per-pixel terms summed in absolute
    value) [N,2], dL/dconics [N,3] and dL/dopacities [N], for loss = sum(image * target[c])."""
    sel = meta["selections"][c]
    w, h = meta["width"], meta["height"]
    ids = sel.host()["ids"]
    valid = ids >= 0
    means2d = meta["means2d"][c].detach().double()
    per_entry = means2d[np.maximum(ids, 0)].clone().requires_grad_(True)
    conics = meta["conics"][c].detach().double().requires_grad_(True)
    opac = torch.tensor(opacities, dtype=torch.float64, requires_grad=True)
    image, _ = blend_ref.render_rays(per_entry, conics, opac, torch.tensor(colors, dtype=torch.float64), ids,
                                     all_pixels(w, h), sel.sampler != "volume")
    (image * target[c].reshape(image.shape).double()).sum().backward()
    entry = per_entry.grad.numpy()[valid]
    grad, absgrad = np.zeros((len(opacities), 2)), np.zeros((len(opacities), 2))
    np.add.at(grad, ids[valid], entry)
    np.add.at(absgrad, ids[valid], np.abs(entry))
    return grad, absgrad, conics.grad.numpy(), opac.grad.numpy()


def assert_close_scaled(got, want, name, rel=2e-4):
    got, want = np.asarray(got, np.float64), np.asarray(want, np.float64)
    scale = float(np.abs(want).max())
    assert scale > 0, name
    np.testing.assert_allclose(got, want, atol=rel * scale, rtol=1e-3, err_msg=name)


@pytest.mark.parametrize("sampler,k", SAMPLERS_K)
def test_2d_meta_gradients_and_absgrad_equal_twin(random_scene, sampler, k):
    rng = np.random.default_rng(1)
    colors = rng.random((len(random_scene[0]), 3)).astype(np.float32)
    _, _, meta, target = render(random_scene, colors, sampler, k, absgrad=True)
    n = len(colors)
    assert meta["means2d"].shape == (2, n, 2) and meta["means2d"].grad.shape == (2, n, 2)
    assert meta["means2d"].absgrad.shape == (2, n, 2)
    for c in range(2):
        grad, absgrad, d_conics, d_opac = twin_splat_grads(meta, c, colors, target, random_scene[3])
        assert_close_scaled(meta["means2d"].grad[c], grad, "means2d")
        assert_close_scaled(meta["means2d"].absgrad[c], absgrad, "absgrad")
        assert_close_scaled(meta["conics"].grad[c], d_conics, "conics")
        assert_close_scaled(meta["opacities"].grad[c], d_opac, "opacities")
    assert (meta["means2d"].absgrad >= meta["means2d"].grad.abs()).all()
    culled = meta["radii"][..., 0] == 0
    assert culled.any() and (meta["means2d"].grad[culled] == 0).all() and (meta["means2d"].absgrad[culled] == 0).all()


def test_absgrad_exceeds_grad_where_pixels_disagree(random_scene):
    """Per-pixel terms of opposite signs cancel in .grad and not in .absgrad: on a real render
    most visible Gaussians have absgrad well above |grad|."""
    colors = np.random.default_rng(2).random((len(random_scene[0]), 3)).astype(np.float32)
    _, _, meta, _ = render(random_scene, colors, absgrad=True, packed=True)
    grad, absgrad = meta["means2d"].grad, meta["means2d"].absgrad
    assert grad.shape == absgrad.shape == (len(meta["gaussian_ids"]), 2)
    assert (absgrad >= grad.abs()).all() and (absgrad > 2 * grad.abs()).float().mean() > 0.3


def test_means2d_gradients_are_bitwise_deterministic(random_scene):
    colors = np.random.default_rng(3).random((len(random_scene[0]), 8)).astype(np.float32)
    runs = []
    for _ in range(2):
        inputs, _, meta, _ = render(random_scene, colors, "quantile", 6, absgrad=True, packed=True)
        runs.append([t.numpy().tobytes() for t in (meta["means2d"].grad, meta["means2d"].absgrad,
                                                   meta["conics"].grad, *(x.grad for x in inputs))])
    assert runs[0] == runs[1]


@pytest.mark.parametrize("sampler,k", [("volume", 40), ("quantile", 5)])
def test_packed_and_dense_agree(random_scene, sampler, k):
    colors = np.random.default_rng(4).random((len(random_scene[0]), 3)).astype(np.float32)
    (d_in, d_img, dense, _), (p_in, p_img, packed, _) = (
        render(random_scene, colors, sampler, k, packed=p, absgrad=True, render_mode="RGB+D") for p in (False, True))
    n = len(colors)
    assert torch.equal(d_img, p_img)
    cam, gid = packed["camera_ids"], packed["gaussian_ids"]
    assert dense["camera_ids"] is None and dense["gaussian_ids"] is None
    visible = dense["radii"][..., 0] > 0
    assert torch.equal(torch.stack(torch.nonzero(visible, as_tuple=True)), torch.stack([cam, gid]))
    assert torch.equal(packed["batch_ids"], torch.zeros_like(gid))
    for key in ("radii", "means2d", "conics", "depths", "opacities"):
        assert torch.equal(packed[key].detach(), dense[key].detach()[cam, gid]), key
    for key in ("means2d", "conics", "opacities", "depths"):
        assert torch.equal(packed[key].grad, dense[key].grad[cam, gid]), key
        assert (dense[key].grad[~visible] == 0).all(), key
    assert torch.equal(packed["means2d"].absgrad, dense["means2d"].absgrad[cam, gid])
    for a, b in zip(d_in, p_in):
        assert torch.equal(a.grad, b.grad)
    assert torch.equal(packed["isect_offsets"], dense["isect_offsets"])
    assert torch.equal(packed["isect_ids"], dense["isect_ids"])
    assert torch.equal(cam[packed["flatten_ids"].long()] * n + gid[packed["flatten_ids"].long()],
                       dense["flatten_ids"].long())
    assert torch.equal(packed["tiles_per_gauss"], dense["tiles_per_gauss"][cam, gid])


def test_meta_intersections_are_gsplats_layout(random_scene):
    """isect_offsets index one flatten_ids over all cameras; each camera's slice of it is its tile
    lists (camera * N + Gaussian), the tiles per Gaussian are their histogram, and the isect_ids
    order as gsplat's sort keys (camera, tile, depth)."""
    m, q, s, o, v, K, w, h = random_scene
    viewmats, Ks = turned_cameras(v, K)
    _, _, meta = qr_cl.rasterization(*tensors(m, q, s, o, np.ones((len(m), 3))), viewmats, Ks, w, h, packed=False)
    n, offsets, flat = len(m), meta["isect_offsets"].reshape(-1).long(), meta["flatten_ids"].long()
    ends = torch.cat([offsets[1:], torch.tensor([len(flat)])])
    tiles = meta["tile_width"] * meta["tile_height"]
    for c in range(2):
        plan = meta["selections"][c].plan.meta()
        for t in range(tiles):
            start, end = plan["tile_ranges"][t]
            got = flat[offsets[c * tiles + t]:ends[c * tiles + t]]
            assert torch.equal(got, torch.from_numpy(plan["flatten_ids"][start:end]).long() + c * n)
    counts = torch.bincount(flat, minlength=2 * n).reshape(2, n)
    assert torch.equal(meta["tiles_per_gauss"].long(), counts)
    assert (torch.diff(meta["isect_ids"]) >= 0).all()
    assert torch.equal(meta["isect_ids"] >> 32 & ((1 << tiles.bit_length()) - 1),
                       torch.repeat_interleave(torch.arange(tiles).repeat(2), ends - offsets))


def test_radii_are_x_and_y_extents_of_the_twin(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    _, _, meta = qr_cl.rasterization(*tensors(m, q, s, o, np.ones((len(m), 3))), torch.tensor(v)[None],
                                     torch.tensor(K)[None], w, h, packed=False)
    twin = project_ref.project(m, q, s, o, v, K, w, h)
    radii = meta["radii"][0].numpy()
    assert radii.dtype == np.int32 and radii.shape == (len(m), 2)
    assert np.abs(radii - twin["radii"]).max() <= 1 and (radii[:, 0] == radii[:, 1]).mean() < 0.9
    assert ((radii > 0) == (twin["radii"] > 0)).all()


def twin_image(inputs, viewmats: torch.Tensor, K, w, h, meta, sh_degree=None, depth=False):
    """The float64 twin of the render of every camera through the kernel's selections (all
    inputs float64 tensors, viewmats [C,4,4] too, so that it differentiates w.r.t. them), with the
    camera z as a last channel when ``depth`` (render_mode "RGB+D")."""
    means, quats, scales, opacities, colors = inputs
    images = []
    for c in range(len(viewmats)):
        e = project_ref.ewa(means, quats / quats.norm(dim=-1, keepdim=True), scales, viewmats[c], K, w, h)
        rgb = colors
        if sh_degree is not None:
            centre = -(viewmats[c][:3, :3].T @ viewmats[c][:3, 3])
            rgb = sh_ref.sh_to_rgb(means, colors[:, :(sh_degree + 1) ** 2], centre)
        if depth:
            rgb = torch.cat([rgb, e["p"][:, 2:]], 1)
        sel = meta["selections"][c]
        image, _ = blend_ref.render_rays(e["means2d"], e["conics"], opacities, rgb, sel.host()["ids"],
                                         all_pixels(w, h), sel.sampler != "volume")
        images.append(image)
    return torch.stack(images)


@pytest.mark.parametrize("sampler,k,sh_degree,mode", [("volume", 40, None, "RGB"), ("quantile", 5, None, "RGB"),
                                                     ("volume", 40, 2, "RGB"), ("topk", 4, None, "RGB+D")])
def test_viewmat_gradients_equal_twin(random_scene, sampler, k, sh_degree, mode):
    """Gradients w.r.t. viewmats and the Gaussians, through the projection, the SH view directions
    and the depth channel, equal the float64 twin's."""
    m, q, s, o, v, K, w, h = random_scene
    rng = np.random.default_rng(5)
    colors = (rng.normal(0, 0.4, (len(m), 9, 3)) if sh_degree else rng.random((len(m), 3))).astype(np.float32)
    viewmats = turned_cameras(v, K)[0].requires_grad_(True)
    inputs = tensors(m, q, s, o, colors, grad=True)
    image, _, meta = qr_cl.rasterization(*inputs, viewmats, torch.tensor(np.stack([K] * 2)), w, h, sampler=sampler,
                                         k=k, sh_degree=sh_degree, render_mode=mode)
    target = torch.randn(image.shape, generator=torch.Generator().manual_seed(6))
    (image * target).sum().backward()
    twin_views = viewmats.detach().double().requires_grad_(True)
    twin_inputs = [t.detach().double().requires_grad_(True) for t in inputs]
    twin = twin_image(twin_inputs, twin_views, K, w, h, meta, sh_degree, depth=mode == "RGB+D")
    (twin * target.double().reshape(twin.shape)).sum().backward()
    assert viewmats.grad.shape == (2, 4, 4) and (viewmats.grad[:, 3] == 0).all()
    assert_close_scaled(viewmats.grad, twin_views.grad, "viewmats")
    for name, got, want in zip(("means", "quats", "scales", "opacities", "colors"), inputs, twin_inputs):
        assert_close_scaled(got.grad, want.grad, name)


def test_twin_projection_passes_gradcheck_in_the_viewmat():
    rng = np.random.default_rng(7)
    means = torch.tensor(np.c_[rng.uniform(-1, 1, (4, 2)), rng.uniform(2, 4, 4)])
    quats, scales = torch.tensor(rng.standard_normal((4, 4))), torch.tensor(rng.uniform(0.1, 0.5, (4, 3)))
    a = 0.3
    view = torch.tensor([[np.cos(a), 0, np.sin(a), 0.1], [0, 1, 0, -0.2], [-np.sin(a), 0, np.cos(a), 0.3],
                         [0, 0, 0, 1]], requires_grad=True)
    K = np.array([[40.0, 0, 16], [0, 40, 12], [0, 0, 1]])
    for key in ("means2d", "conics", "p"):
        assert torch.autograd.gradcheck(lambda vm: project_ref.ewa(means, quats, scales, vm, K, 32, 24)[key], (view,))


def test_viewmat_gradients_agree_with_finite_differences():
    """Directional derivatives of the (float32) render's loss along the camera's translations and
    rotations: central differences of the kernel render agree with sum(viewmats.grad * D). A
    render is not differentiable where alphas cross 1/255 (skipped) and the gradient, as gsplat's,
    is that of the smooth part, so the scene has few large Gaussians and the loss a smooth target:
    the difference is then a few percent."""
    from tests.conftest import make_random_scene
    m, q, s, o, v, K, w, h = make_random_scene(n=60, seed=3)
    s = s * 2.5
    colors = np.random.default_rng(8).random((len(m), 3)).astype(np.float32)
    ys, xs = np.mgrid[0:h, 0:w]
    target = torch.tensor(np.stack([xs / w, ys / h, (xs + ys) / (w + h)], -1)[None], dtype=torch.float64)
    base = torch.tensor(v, dtype=torch.float64)

    def loss(view: torch.Tensor) -> torch.Tensor:
        image, _, _ = qr_cl.rasterization(*tensors(m, q, s, o, colors), view.float()[None], torch.tensor(K)[None],
                                          w, h)
        return (image.double() * target).sum()
    view = base.float().clone().requires_grad_(True)
    image, _, _ = qr_cl.rasterization(*tensors(m, q, s, o, colors), view[None], torch.tensor(K)[None], w, h)
    (image * target.float()).sum().backward()
    directions = []
    for axis in range(3):
        translation = torch.zeros(4, 4, dtype=torch.float64)
        translation[axis, 3] = 1.0
        omega = torch.zeros(3, dtype=torch.float64)
        omega[axis] = 1.0
        skew = torch.linalg.cross(omega.expand(3, 3), torch.eye(3, dtype=torch.float64)).T   # [omega]_x
        rotation = torch.zeros(4, 4, dtype=torch.float64)
        rotation[:3] = skew @ base[:3]                     # d/dt of exp(t [omega]_x) [R | t]
        directions += [translation, rotation]
    analytic = [float((view.grad.double() * D).sum()) for D in directions]
    scale = max(abs(a) for a in analytic)
    eps = 5e-3
    for D, a in zip(directions, analytic):
        numeric = float((loss(base + eps * D) - loss(base - eps * D)) / (2 * eps))
        assert abs(numeric - a) <= 0.04 * abs(a) + 0.005 * scale, (numeric, a)


@pytest.mark.parametrize("packed,absgrad", [(False, False), (True, False), (True, True)])
def test_gsplats_default_strategy_densifies_through_qr_cl(random_scene, packed, absgrad):
    """gsplat's own DefaultStrategy (step_pre_backward: means2d.retain_grad(); step_post_backward:
    grad2d from meta["means2d"].grad or .absgrad, radii [C,N,2], gaussian_ids, then clone, split
    and prune) runs unchanged on qr_cl.rasterization's meta."""
    strategy_module = pytest.importorskip("gsplat.strategy", reason="gsplat (in the test extra) not installed")
    m, q, s, o, v, K, w, h = random_scene
    params = torch.nn.ParameterDict({
        "means": torch.tensor(m), "quats": torch.tensor(q), "scales": torch.log(torch.tensor(s)),
        "opacities": torch.logit(torch.tensor(o).clamp(0.05, 0.95)),
        "colors": torch.tensor(np.random.default_rng(11).random((len(m), 3)), dtype=torch.float32)})
    optimizers = {key: torch.optim.Adam([p], lr=1e-3) for key, p in params.items()}
    strategy = strategy_module.DefaultStrategy(refine_start_iter=1, refine_every=2, reset_every=1000,
                                               grow_grad2d=1e-6, prune_opa=0.1, absgrad=absgrad, verbose=False)
    strategy.check_sanity(params, optimizers)
    state = strategy.initialize_state(scene_scale=1.0)
    viewmats, Ks = turned_cameras(v, K)
    with torch.no_grad():
        target, _, _ = qr_cl.rasterization(*tensors(m, q, s, o, np.full((len(m), 3), 0.5)), viewmats, Ks, w, h)
    sizes = [len(params["means"])]
    for step in range(5):
        image, _, info = qr_cl.rasterization(params["means"], params["quats"], params["scales"].exp(),
                                             torch.sigmoid(params["opacities"]), params["colors"], viewmats, Ks, w, h,
                                             packed=packed, absgrad=absgrad)
        strategy.step_pre_backward(params, optimizers, state, step, info)
        ((image - target) ** 2).mean().backward()
        strategy.step_post_backward(params, optimizers, state, step, info, packed=packed)
        for opt in optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        sizes.append(len(params["means"]))
    assert sizes[-1] != sizes[0] and max(sizes) > sizes[0], sizes


@pytest.mark.parametrize("sampler,k", [("volume", 40), ("topk", 4)])
def test_gpu_launch_shapes_give_the_same_bytes(random_scene, monkeypatch, sampler, k):
    """The 2-D meta gradients, absgrad and the viewmat gradient (project_backward's per-Gaussian
    shares) are the same bytes in the GPU launch shapes (forced on PoCL) as in the CPU ones."""
    from qr_cl.runtime import runtime
    m, q, s, o, v, K, w, h = random_scene
    colors = np.random.default_rng(12).random((len(m), 3)).astype(np.float32)
    out = {}
    for launch in ("cpu", "gpu"):
        monkeypatch.setattr(runtime(), "gpu_shaped", launch == "gpu")
        viewmats = turned_cameras(v, K)[0].requires_grad_(True)
        inputs, image, meta, _ = render(random_scene, colors, sampler, k, packed=True, absgrad=True,
                                        viewmats=viewmats)
        out[launch] = [t.detach().numpy().tobytes() for t in (image, viewmats.grad, meta["means2d"].grad,
                                                              meta["means2d"].absgrad, meta["conics"].grad,
                                                              *(x.grad for x in inputs))]
    assert out["gpu"] == out["cpu"]


@pytest.mark.parametrize("sampler,k", [("volume", 40), ("quantile", 5)])
def test_extra_signals_share_one_selection(random_scene, monkeypatch, sampler, k):
    """RGB (+ depth) and 64-D extra signals from one call equal two calls (RGB; the signals as
    colors), values and gradients, with one plan and one selection per camera instead of two."""
    from qr_cl.render import engine
    m, q, s, o, v, K, w, h = random_scene
    rng = np.random.default_rng(13)
    colors, signals = rng.random((len(m), 3)).astype(np.float32), rng.normal(size=(len(m), 64)).astype(np.float32)
    viewmats, Ks = turned_cameras(v, K)
    bg = torch.tensor([[0.1, 0.2, 0.3]] * 2)
    made, select = [], engine.select_and_blend_rays
    monkeypatch.setattr(engine, "select_and_blend_rays", lambda *a, **kw: made.append(1) or select(*a, **kw))
    one = tensors(m, q, s, o, colors, signals, grad=True)
    image, alpha, meta = qr_cl.rasterization(*one[:5], viewmats, Ks, w, h, sampler=sampler, k=k, backgrounds=bg,
                                             render_mode="RGB+ED", extra_signals=one[5])
    extra = meta["render_extra_signals"]
    assert image.shape == (2, h, w, 4) and extra.shape == (2, h, w, 64) and len(made) == 2
    target, target_extra = torch.randn(image.shape), torch.randn(extra.shape)
    ((image * target).sum() + (extra * target_extra).sum()).backward()
    two = tensors(m, q, s, o, colors, signals, grad=True)
    want, want_alpha, _ = qr_cl.rasterization(*two[:5], viewmats, Ks, w, h, sampler=sampler, k=k, backgrounds=bg,
                                              render_mode="RGB+ED")
    want_extra, _, _ = qr_cl.rasterization(*two[:4], two[5], viewmats, Ks, w, h, sampler=sampler, k=k)
    assert len(made) == 6
    ((want * target).sum() + (want_extra * target_extra).sum()).backward()
    torch.testing.assert_close(image, want, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(extra, want_extra, rtol=1e-6, atol=1e-6)
    assert torch.equal(alpha, want_alpha)
    for name, a, b in zip(("means", "quats", "scales", "opacities", "colors", "extra_signals"), one, two):
        # the geometry's terms are summed in another float32 order (one dot product over all channels)
        torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-4 * float(b.grad.abs().max()), msg=name)
    with pytest.raises(ValueError, match="extra_signals"):
        qr_cl.rasterization(*one[:5], viewmats, Ks, w, h, extra_signals=torch.zeros(3, 4))


def test_the_examples_densifier_grows_and_prunes(random_scene, monkeypatch):
    """examples/fit_and_train_gsnet.py's gsplat-style Densifier on qr-cl's packed meta: it clones,
    splits and prunes, and keeps the parameters, the optimizer's groups and Adam's moments in step."""
    import importlib.util
    import sys
    from pathlib import Path
    path = Path(__file__).resolve().parents[2] / "examples" / "fit_and_train_gsnet.py"
    spec = importlib.util.spec_from_file_location("fit_and_train_gsnet", path)
    example = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, example)
    spec.loader.exec_module(example)
    m, q, s, o, v, K, w, h = random_scene
    params = {"means": torch.tensor(m), "quats": torch.tensor(q), "log_scales": torch.log(torch.tensor(s)),
              "logit_opacities": torch.logit(torch.tensor(o).clamp(0.05, 0.95)),
              "colors": torch.full((len(m), 3), 0.5)}
    for p in params.values():
        p.requires_grad_(True)
    opt = torch.optim.Adam([{"params": [p], "lr": 1e-3} for p in params.values()])
    densifier = example.Densifier(extent=4.0, grad2d=1e-7, scale3d=0.03, opacity=0.3, start=1, every=2, stop=6)
    viewmats, Ks = turned_cameras(v, K)
    with torch.no_grad():
        target, _, _ = qr_cl.rasterization(*tensors(m, q, s, o, np.full((len(m), 3), 0.3)), viewmats, Ks, w, h)
    for step in range(7):
        image, _, meta = qr_cl.rasterization(params["means"], params["quats"], params["log_scales"].exp(),
                                             torch.sigmoid(params["logit_opacities"]), params["colors"],
                                             viewmats, Ks, w, h)
        opt.zero_grad()
        densifier.before_backward(meta)
        ((image - target) ** 2).mean().backward()
        densifier.after_backward(step, meta, params, opt)
        opt.step()
    steps, cloned, split, pruned, sizes = zip(*densifier.history)
    assert steps == (2, 4) and sum(cloned) > 0 and sum(split) > 0 and sum(pruned) > 0
    assert sizes[-1] == len(params["means"]) != len(m)
    for group, p in zip(opt.param_groups, params.values()):
        assert group["params"][0] is p and opt.state[p]["exp_avg"].shape == p.shape
