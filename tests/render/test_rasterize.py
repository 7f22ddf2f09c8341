"""rasterize and render_volume_fused end to end against the twins: colors from SH by the view
direction, empty scenes, named input errors, the real scenes, the render meta."""
import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.scene import orbit_cameras
from qr_cl.stages import sh_ref, vrender_ref
from tests.twins import H, W, assert_projection_matches, hostile_scene, origin_camera, render_both


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


@pytest.mark.parametrize("scene,channels", [("fox", 3), pytest.param("fox", 64, marks=pytest.mark.slow),
                                            pytest.param("donut", 3, marks=pytest.mark.slow),
                                            pytest.param("donut", 64, marks=pytest.mark.slow)])
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
