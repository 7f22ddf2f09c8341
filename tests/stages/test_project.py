"""Projection (project.cl) against its float64 twin (qr_cl.stages.project_ref) on a hostile scene."""
from tests.twins import H, W, assert_projection_matches, hostile_scene, origin_camera, render_both


def test_projection_matches_reference_on_hostile_scene():
    g, cam = hostile_scene(), origin_camera()
    (_, _, meta), (*_, proj) = render_both(g, g.rgb, cam)
    assert_projection_matches(meta, proj)
    radii = meta["radii"][:, 0]
    assert meta["radii"].shape == (len(g), 2) and meta["radii"].dtype == "int32"
    assert (meta["radii"][:20] == 0).all(), "Gaussians behind the camera must be culled"
    assert (meta["radii"][30:35] > max(W, H)).all(), "huge Gaussians cover the image"
    assert (meta["depths"][20:30][radii[20:30] > 0] >= 0.01).all()
    assert 0 < (radii[20:30] > 0).sum() < 10, "the near plane splits the straddling Gaussians"


def test_project_backward_equals_twin_gradients_on_hostile_scene():
    """project_backward (d mean2d, d conic, d depth -> d means, quats, scales and, with
    view_grads, the viewmat's per-Gaussian shares summed) against torch autograd through the
    float64 twin project_ref.ewa, on a turned camera over the hostile scene (near plane, views
    clamped at 1.3x the field of view, huge and tiny Gaussians); culled Gaussians get zeros."""
    import numpy as np
    import torch

    from qr_cl.render import rasterize_plan
    from qr_cl.runtime import SPLAT, SPLAT_FLOATS, runtime, to_device
    from qr_cl.stages import project_ref
    from qr_cl.stages.project import project_backward
    g = hostile_scene()
    a = 0.2
    turn = np.array([[np.cos(a), 0, np.sin(a), 0.3], [0, 1, 0, -0.1], [-np.sin(a), 0, np.cos(a), 0.2], [0, 0, 0, 1]])
    cam = origin_camera()
    viewmat = (turn @ cam.viewmat).astype(np.float32)
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, viewmat, cam.K, W, H)
    visible = plan.radii.get()[:, 0] > 0
    rng = np.random.default_rng(0)
    d_splats = np.where(visible[:, None], rng.normal(size=(len(g), SPLAT_FLOATS)), 0).astype(np.float32)
    d_splats[:, [SPLAT.opacity, SPLAT.sigma_max]] = 0
    rt = runtime()
    dev = [to_device(rt, x) for x in (g.means, g.quats, g.scales)]
    d_means, d_quats, d_scales, d_view = project_backward(rt, *dev, plan.radii, viewmat, cam.K, W, H,
                                                          to_device(rt, d_splats), view_grads=True)
    twin = [torch.tensor(x, dtype=torch.float64, requires_grad=True) for x in (g.means, g.quats, g.scales, viewmat)]
    e = project_ref.ewa(*twin, cam.K, W, H)
    d = torch.tensor(d_splats, dtype=torch.float64)
    loss = (e["means2d"] * d[:, SPLAT.mean]).sum(1) + (e["conics"] * d[:, SPLAT.conic]).sum(1) + e["p"][:, 2] * d[:, SPLAT.depth]
    loss[visible].sum().backward()
    for name, got, want in (("means", d_means.get(), twin[0].grad), ("quats", d_quats.get(), twin[1].grad),
                            ("scales", d_scales.get(), twin[2].grad)):
        want = want.numpy()
        scale = np.abs(want).max(1, keepdims=True) + 1e-12
        np.testing.assert_allclose(got / scale, want / scale, atol=2e-3, err_msg=name)
        assert (got[~visible] == 0).all(), name
    np.testing.assert_allclose(d_view, twin[3].grad.numpy(), rtol=1e-3, atol=1e-3 * np.abs(d_view).max())
    assert (d_view[3] == 0).all() and np.abs(d_view[:3]).max() > 0
    _, _, _, none = project_backward(rt, *dev, plan.radii, viewmat, cam.K, W, H, to_device(rt, d_splats))
    assert none is None
