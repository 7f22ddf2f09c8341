"""The fused V-Render (vrender.cl) against its float64 twin (qr_cl.stages.vrender_ref) on the
kernel's own projection and tile lists."""
import numpy as np
import pytest

from tests.twins import H, W, hostile_scene, origin_camera, render_both


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
