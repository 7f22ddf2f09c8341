"""Cameras: 3DGS cameras.json (camera-to-world), V3DG/NeRF layouts, orbits, errors."""
import json

import numpy as np
import pytest

import qr_cl
from qr_cl.scene import SceneFormatError, load_layout_instance, orbit_cameras


def pixel_of(cam, points):
    p = points @ cam.viewmat[:3, :3].T + cam.viewmat[:3, 3]
    return np.stack([cam.fx * p[:, 0] / p[:, 2] + cam.cx, cam.fy * p[:, 1] / p[:, 2] + cam.cy], 1), p[:, 2]


def test_gs_cameras_json_is_camera_to_world(tmp_path):
    # camera at (1, 2, 3) whose axes are world x (right), -z (down), y (forward)
    rot = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], float)
    entry = {"id": 0, "img_name": "a", "width": 200, "height": 100, "position": [1, 2, 3],
             "rotation": rot.tolist(), "fx": 150.0, "fy": 160.0}
    (tmp_path / "cameras.json").write_text(json.dumps([entry]))
    cam, = qr_cl.load_cameras(tmp_path / "cameras.json")
    assert (cam.width, cam.height, cam.cx, cam.cy) == (200, 100, 100, 50)
    np.testing.assert_allclose(cam.position, [1, 2, 3], atol=1e-6)
    uv, z = pixel_of(cam, np.array([[1, 7, 3], [2, 7, 3], [1, 7, 2]], float))
    np.testing.assert_allclose(uv[0], [100, 50], atol=1e-4)     # straight ahead: the centre
    assert z[0] == pytest.approx(5) and uv[1, 0] > 100 and uv[2, 1] > 50  # +x right, -z down


def test_layout_instance_only_for_layouts(tmp_path):
    (tmp_path / "c.json").write_text("[]")
    assert load_layout_instance(tmp_path / "c.json") is None


def test_cameras_json_errors(tmp_path):
    (tmp_path / "c.json").write_text(json.dumps([{"width": 1, "height": 1}]))
    with pytest.raises(SceneFormatError, match=r"c\.json: camera 0 .* has no 'rotation'"):
        qr_cl.load_cameras(tmp_path / "c.json")
    (tmp_path / "d.json").write_text("{not json")
    with pytest.raises(SceneFormatError, match="not valid JSON"):
        qr_cl.load_cameras(tmp_path / "d.json")


def test_orbit_cameras_look_at_the_centre():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(1000, 3)) * [1, 2, 0.5] + [3, 0, 1]
    for cam in orbit_cameras(pts, 6, 320, 240):
        uv, z = pixel_of(cam, np.median(pts, 0)[None])
        np.testing.assert_allclose(uv[0], [160, 120], atol=1e-3)
        inside = (z > 0) & (np.abs(pixel_of(cam, pts)[0] - [160, 120]) < [160, 120]).all(1)
        assert inside.mean() > 0.95


def test_donut_layout_camera_frames_the_donut(donut):
    gaussians, cameras = donut
    cam, = cameras
    assert (cam.width, cam.height) == (1920, 1080) and cam.fx == pytest.approx(2317.64, abs=0.01)
    uv, z = pixel_of(cam, gaussians.means.astype(np.float64))
    assert (z > 0).all()
    # SOURCE.md: all centres in frame, u 434..1480, v 109..671 at full resolution
    assert uv[:, 0].min() == pytest.approx(434, abs=3) and uv[:, 0].max() == pytest.approx(1480, abs=3)
    assert uv[:, 1].min() == pytest.approx(109, abs=3) and uv[:, 1].max() == pytest.approx(671, abs=3)
