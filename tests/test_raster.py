"""Kernels vs the numpy reference: projection, binning, V-Render, SH colours."""
import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.render import rasterize_plan
from qr_cl.runtime import runtime, to_device
from qr_cl.scene import Gaussians, look_at, orbit_cameras
from qr_cl.stages import binning_ref, project_ref, sh_colors, sh_ref, vrender_ref
from qr_cl.stages import host_sort
from qr_cl.stages.sh import sh_backward

W, H = 96, 72


def hostile_scene(n=600, seed=0, degree=0) -> Gaussians:
    """Random Gaussians in front of a camera at the origin looking down +z, plus edge cases:
    behind the camera, at the near plane, huge (covering the image) and tiny ones."""
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(1, 6, n)]
    scales = np.exp(rng.uniform(-4, -1, (n, 3)))
    means[:20, 2] = -rng.uniform(0.1, 3, 20)                 # behind the camera
    means[20:30, 2] = 0.01 + rng.choice([-1, 1], 10) * 2e-4  # straddling the near plane (0.01)
    means[20:30, :2] *= 0.005
    scales[30:35] = rng.uniform(3, 10, (5, 3))               # huge: covers the whole image
    means[30:35] = [[0, 0, 4]] * 5
    scales[35:60] = 1e-5                                     # tiny
    q = rng.normal(size=(n, 4))
    sh = rng.normal(0, 0.6, (n, (degree + 1) ** 2, 3))
    return Gaussians(means.astype(np.float32), (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                     scales.astype(np.float32), rng.uniform(0.05, 1, n).astype(np.float32), sh.astype(np.float32))


def origin_camera():
    return look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 80.0, 82.0, W, H)


def assert_projection_matches(meta, proj):
    vis = proj["radii"] > 0
    mismatch = meta["radii"] != proj["radii"]
    # a radius may differ only where float32 and float64 round 3*sqrt(lambda) to different ceilings
    assert mismatch.sum() <= max(1, int(0.002 * len(mismatch))), f"{mismatch.sum()} radii differ"
    both = vis & ~mismatch
    for key in ("means2d", "conics", "depths"):
        np.testing.assert_allclose(meta[key][both], proj[key][both], rtol=1e-4, atol=1e-4, err_msg=key)
    np.testing.assert_array_equal(meta["means2d"][~vis & ~mismatch], 0)


def render_both(g, features, cam, background=None):
    """The kernel render, and the reference V-Render of the kernel's own projection and tile
    lists (so the blend is compared without projection rounding; those are tested apart)."""
    img, alpha, meta = qr_cl.render_volume_fused(g.means, g.quats, g.scales, g.opacities, features,
                                                 cam.viewmat, cam.K, cam.width, cam.height,
                                                 background=background)
    proj = project_ref.project(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, cam.width, cam.height)
    rimg, ralpha, rdepth = vrender_ref.vrender(meta, meta["tile_ranges"], meta["flatten_ids"], features,
                                       cam.width, cam.height, background)
    return (img.numpy(), alpha.numpy(), meta), (rimg, ralpha, rdepth, proj)


def test_projection_matches_reference_on_hostile_scene():
    g, cam = hostile_scene(), origin_camera()
    (_, _, meta), (*_, proj) = render_both(g, g.rgb, cam)
    assert_projection_matches(meta, proj)
    radii = meta["radii"]
    assert (radii[:20] == 0).all(), "Gaussians behind the camera must be culled"
    assert (radii[30:35] > max(W, H)).all(), "huge Gaussians cover the image"
    assert (meta["depths"][20:30][radii[20:30] > 0] >= 0.01).all()
    assert 0 < (radii[20:30] > 0).sum() < 10, "the near plane splits the straddling Gaussians"


def test_binning_matches_reference():
    g, cam = hostile_scene(seed=1), origin_camera()
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, W, H)
    proj = project_ref.project(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, W, H)
    ranges, ids = binning_ref.bin_and_sort(proj, W, H)
    assert plan.n_keys == len(ids) == proj["tiles_touched"].sum()
    np.testing.assert_array_equal(plan.ranges.get(), ranges)
    np.testing.assert_array_equal(plan.ids.get()[:plan.n_keys], ids)


def tilted_scene(n=150, seed=0) -> Gaussians:
    """Elongated, tilted Gaussians of all sizes in front of the origin camera: ellipses that leave
    many tiles of their bounding rectangle untouched, some taller than SPAN_ROWS tile rows at
    640x480 (their spans are computed again in the binning passes instead of stored)."""
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(2, 5, n)]
    scales = np.c_[np.exp(rng.uniform(-3, 0.5, n)), np.exp(rng.uniform(-5, -3, (n, 2)))]
    q = rng.normal(size=(n, 4))
    return Gaussians(means.astype(np.float32), (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                     scales.astype(np.float32), rng.uniform(0.05, 1, n).astype(np.float32),
                     np.zeros((n, 1, 3), np.float32))


def test_tile_spans_drop_only_tiles_the_ellipse_never_blends():
    """Brute force, in float64: no pixel of a tile that a Gaussian's row spans leave out of its
    rectangle has sigma <= sigma_max there (so no pixel of it would blend the Gaussian), and the
    spans do leave tiles out."""
    g, cam = tilted_scene(), look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 500.0, 500.0, 640, 480)
    proj = project_ref.project(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, 640, 480)
    tiles_x = 40
    dropped = 0
    for i in np.flatnonzero(proj["radii"] > 0):
        x0, y0, x1, y1 = proj["rects"][i]
        kept = {(ty, tx) for ty, a, b in project_ref.tile_spans(proj["means2d"][i], proj["conics"][i],
                                                                 proj["opacities"][i], proj["rects"][i], tiles_x)
                for tx in range(a, b)}
        a, b, c = proj["conics"][i]
        sigma_max = np.log(proj["opacities"][i] / qr_cl.runtime.ALPHA_MIN)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                if (ty, tx) in kept:
                    continue
                dropped += 1
                ys, xs = np.mgrid[ty * 16:ty * 16 + 16, tx * 16:tx * 16 + 16] + 0.5
                dx, dy = proj["means2d"][i, 0] - xs, proj["means2d"][i, 1] - ys
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                assert sigma.min() > sigma_max, f"Gaussian {i} blends in dropped tile ({tx}, {ty})"
    rect_tiles = np.prod(proj["rects"][:, 2:] - proj["rects"][:, :2], axis=1)[proj["radii"] > 0].sum()
    assert dropped > 0.2 * rect_tiles, (dropped, rect_tiles)


def test_binning_of_tall_tilted_ellipses_matches_reference():
    """Stored spans (rectangles of at most SPAN_ROWS rows) and spans computed again (taller ones)
    give the twin's tile lists, with fewer pairs than the rectangles. The twin bins the kernel's
    own splats: the float32 conic of a Gaussian hundreds of pixels wide differs from the float64
    one by ~1e-3, enough to move a span's end across a tile edge (the projection is tested apart)."""
    g, cam = tilted_scene(seed=1), look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 500.0, 500.0, 640, 480)
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, 640, 480)
    proj = project_ref.project(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, 640, 480)
    meta = plan.meta()
    np.testing.assert_array_equal(meta["radii"] > 0, proj["radii"] > 0)
    proj.update({k: meta[k].astype(np.float64) for k in ("means2d", "conics", "depths", "opacities")})
    rows = (proj["rects"][:, 3] - proj["rects"][:, 1])[proj["radii"] > 0]
    assert (rows > 24).sum() >= 3 and (rows <= 24).sum() >= 30, "both kinds of rectangles"
    ranges, ids = binning_ref.bin_and_sort(proj, 640, 480)
    np.testing.assert_array_equal(plan.ranges.get(), ranges)
    np.testing.assert_array_equal(plan.ids.get()[:plan.n_keys], ids)
    rect_pairs = np.prod(proj["rects"][:, 2:] - proj["rects"][:, :2], axis=1)[proj["radii"] > 0].sum()
    assert plan.n_keys < 0.8 * rect_pairs


def test_host_sort_is_stable_and_restores_torchs_thread_count():
    """The binning's host sort equals numpy's stable argsort (ties keep their index order) and
    leaves torch's thread count as it found it, also when the sort fails."""
    keys = torch.from_numpy(np.random.default_rng(0).integers(0, 50, 10_000).astype(np.int32))
    threads = torch.get_num_threads()
    sorted_keys, order = host_sort(keys)
    np.testing.assert_array_equal(order.numpy(), np.argsort(keys.numpy(), kind="stable"))
    np.testing.assert_array_equal(sorted_keys.numpy(), np.sort(keys.numpy()))
    with pytest.raises(RuntimeError):
        host_sort(keys, out=(torch.empty(3, dtype=torch.float64), torch.empty(3, dtype=torch.int64)))
    assert torch.get_num_threads() == threads


@pytest.mark.parametrize("channels", [1, 3, 5, 64, 512])
def test_vrender_matches_reference(channels):
    g, cam = hostile_scene(seed=channels), origin_camera()
    features = np.random.default_rng(channels).normal(size=(len(g), channels)).astype(np.float32)
    (img, alpha, meta), (rimg, ralpha, rdepth, proj) = render_both(g, features, cam)
    assert img.shape == (H, W, channels) and alpha.shape == (H, W, 1)
    assert np.abs(img - rimg).max() < 1e-4
    assert np.abs(alpha - ralpha).max() < 1e-4
    assert np.abs(meta["depth"] - rdepth).max() < 1e-4 * max(1, rdepth.max())
    assert (ralpha > 0.5).mean() > 0.3 and np.abs(rimg).max() > 0.1  # the test sees real content


def test_background_is_blended_with_the_remaining_transmittance():
    g, cam = hostile_scene(n=200, seed=3), origin_camera()
    bg = np.array([0.2, -0.5, 1.0], np.float32)
    (img, alpha, _), (rimg, ralpha, *_) = render_both(g, g.rgb, cam, background=bg)
    assert np.abs(img - rimg).max() < 1e-4
    (plain, *_), _ = render_both(g, g.rgb, cam)
    np.testing.assert_allclose(img - plain, (1 - alpha) * bg, atol=1e-5)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_colours_match_reference(degree):
    g = hostile_scene(n=300, seed=degree, degree=degree)
    campos = np.array([0.3, -0.2, -1.0])
    rt = runtime()
    rgb = sh_colors(rt, to_device(rt, g.means), g.sh, campos).get()
    np.testing.assert_allclose(rgb[:, :3], sh_ref.sh_to_rgb(g.means, g.sh, campos), atol=1e-5)
    assert (rgb[:, 3] == 0).all()


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_sh_backward_matches_the_twins_autograd(degree):
    """sh_backward (sh.cl) against autograd of the float64 twin: d coefficients and d means,
    including Gaussians whose colour is clamped at 0 (no gradient through the clamp)."""
    g = hostile_scene(n=300, seed=degree, degree=degree)
    g.sh[::10] -= 3.0                                            # some colours clamped at 0
    campos = np.array([0.3, -0.2, -1.0], np.float32)
    rt = runtime()
    means = to_device(rt, g.means)
    colors = sh_colors(rt, means, g.sh, campos)
    d_rgb = np.random.default_rng(degree).normal(size=(len(g.means), 3)).astype(np.float32)
    d_sh, d_means = sh_backward(rt, means, g.sh, campos, colors, d_rgb)
    m, c = (torch.tensor(a, dtype=torch.float64, requires_grad=True) for a in (g.means, g.sh))
    rgb = sh_ref.sh_to_rgb(m, c, torch.tensor(campos, dtype=torch.float64))
    assert (rgb == 0).any()
    (rgb * torch.from_numpy(d_rgb).double()).sum().backward()
    want_means = m.grad.numpy() if m.grad is not None else np.zeros_like(d_means)
    np.testing.assert_allclose(d_sh, c.grad.numpy(), atol=1e-5 * float(c.grad.abs().max()))
    np.testing.assert_allclose(d_means, want_means, atol=1e-5 * max(float(np.abs(want_means).max()), 1e-3))


def test_rgb_render_from_sh_uses_the_view_direction():
    g = hostile_scene(n=400, seed=7, degree=2)
    cam = origin_camera()
    img, _, _ = qr_cl.rasterize(g.means, g.quats, g.scales, g.opacities, torch.from_numpy(g.sh),
                                cam.viewmat, cam.K, W, H, sh_degree=2)
    rgb = sh_ref.sh_to_rgb(g.means, g.sh, cam.position)
    rimg, *_ = vrender_ref.render(g.means, g.quats, g.scales, g.opacities, rgb, cam.viewmat, cam.K, W, H)
    assert np.abs(img.numpy() - rimg).max() < 1e-4


def test_empty_scene_and_nothing_visible():
    cam = origin_camera()
    empty = np.zeros((0, 3), np.float32)
    img, alpha, meta = qr_cl.rasterize(empty, np.zeros((0, 4)), empty, np.zeros(0), np.zeros((0, 4)),
                                       cam.viewmat, cam.K, W, H, background=np.ones(4))
    assert img.shape == (H, W, 4) and (img.numpy() == 1).all() and (alpha.numpy() == 0).all()
    g = hostile_scene(n=60)
    g.means[:, 2] = -1
    img, alpha, meta = qr_cl.rasterize(g.means, g.quats, g.scales, g.opacities, g.rgb,
                                       cam.viewmat, cam.K, W, H)
    assert meta["n_keys"] == 0 and (img.numpy() == 0).all() and (alpha.numpy() == 0).all()


def test_bad_input_shapes_are_named():
    g, cam = hostile_scene(n=60), origin_camera()
    with pytest.raises(ValueError, match="quats has shape"):
        qr_cl.rasterize(g.means, g.quats[:, :3], g.scales, g.opacities, g.rgb, cam.viewmat, cam.K, W, H)
    with pytest.raises(ValueError, match="2049 channels"):
        qr_cl.rasterize(g.means, g.quats, g.scales, g.opacities, np.zeros((60, 2049)), cam.viewmat, cam.K, W, H)


@pytest.mark.parametrize("scene", ["fox", "donut"])
@pytest.mark.parametrize("channels", [3, 64])
def test_real_scenes_match_reference(request, scene, channels):
    if scene == "fox":
        g = request.getfixturevalue("fox")
        cam = orbit_cameras(g.means, 8, 160, 120)[3]
    else:
        g, (cam,) = request.getfixturevalue("donut")
        cam = cam.resized(192, 108)
    features = g.rgb if channels == 3 else \
        np.random.default_rng(0).random((len(g), channels)).astype(np.float32)
    (img, alpha, meta), (rimg, ralpha, rdepth, proj) = render_both(g, features, cam)
    assert_projection_matches(meta, proj)
    assert np.abs(img - rimg).max() < 1e-4
    assert np.abs(alpha - ralpha).max() < 1e-4
    assert (ralpha > 0.5).mean() > 0.05
    # End to end against the all-reference pipeline (float64 projection): only pixels where an
    # alpha lands within rounding of 1/255 (or T of 1e-4) may differ by more than 1e-4.
    full, *_ = vrender_ref.render(g.means, g.quats, g.scales, g.opacities, features, cam.viewmat, cam.K,
                          cam.width, cam.height)
    differing = (np.abs(img - full).max(-1) > 1e-4).mean()
    assert differing < 1e-3, f"{differing:.2%} of pixels differ from the float64 pipeline"


def test_render_meta_is_the_plan_meta_copied_on_first_access(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    features = np.random.default_rng(3).random((len(m), 5), dtype=np.float32)
    _, _, meta = qr_cl.rasterize(m, q, s, o, features, v, K, w, h, sampler="quantile", k=4)
    assert meta._host is None                         # nothing copied before an entry is read
    want = meta["selection"].plan.meta()
    assert set(meta) == set(want) | {"selection"} and len(meta) == len(want) + 1
    for key, value in want.items():
        np.testing.assert_array_equal(meta[key], value)
    with pytest.raises(KeyError):
        meta["depth"]
    _, _, fused_meta = qr_cl.render_volume_fused(m, q, s, o, features, v, K, w, h)
    assert fused_meta["depth"].shape == (h, w, 1) and set(fused_meta) == set(want) | {"depth"}
