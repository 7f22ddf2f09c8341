"""Projection (project.cl) against its float64 twin (qr_cl.stages.project_ref) on a hostile scene."""
from tests.twins import H, W, assert_projection_matches, hostile_scene, origin_camera, render_both


def test_projection_matches_reference_on_hostile_scene():
    g, cam = hostile_scene(), origin_camera()
    (_, _, meta), (*_, proj) = render_both(g, g.rgb, cam)
    assert_projection_matches(meta, proj)
    radii = meta["radii"]
    assert (radii[:20] == 0).all(), "Gaussians behind the camera must be culled"
    assert (radii[30:35] > max(W, H)).all(), "huge Gaussians cover the image"
    assert (meta["depths"][20:30][radii[20:30] > 0] >= 0.01).all()
    assert 0 < (radii[20:30] > 0).sum() < 10, "the near plane splits the straddling Gaussians"
