"""SceneSplat folders: reading, writing, round trips through PLY, the same pixels, hostile files."""
import json

import numpy as np
import pytest

import qr_cl
from qr_cl.render import render_volume_fused
from qr_cl.runtime import SH_C0
from qr_cl.scene import (Gaussians, SceneFormatError, SceneSplatFolder, load_cameras, load_scene, orbit_cameras,
                         save_scenesplat)

from ..conftest import make_random_scene


def scene_gaussians(n: int = 300, degree: int = 0, seed: int = 0) -> Gaussians:
    """Random Gaussians in front of an identity camera (conftest's scene) with random colours."""
    means, quats, scales, opacities, *_ = make_random_scene(n, seed)
    rng = np.random.default_rng(seed)
    return Gaussians(means, quats, scales, opacities, rng.normal(0, 0.8, (n, (degree + 1) ** 2, 3)).astype(np.float32))


def scenesplat_files(folder, g: Gaussians, **extra) -> None:
    """SceneSplat's own files only (no sh.npy): colour as uint8, opacity [N,1] as Pointcept reads it."""
    rgb = np.clip(0.5 + SH_C0 * g.sh[:, 0].astype(np.float64), 0, 1)
    arrays = {"coord": g.means, "color": np.round(rgb * 255).astype(np.uint8), "opacity": g.opacities[:, None],
              "quat": g.quats, "scale": g.scales, **extra}
    folder.mkdir(exist_ok=True)
    for name, a in arrays.items():
        np.save(folder / f"{name}.npy", a)


@pytest.mark.parametrize("degree", [0, 2])
def test_folder_round_trip_is_exact(tmp_path, degree):
    g = scene_gaussians(degree=degree)
    save_scenesplat(tmp_path / "s", g)
    h = SceneSplatFolder(tmp_path / "s").gaussians
    for field in ("means", "quats", "scales", "opacities", "sh"):
        np.testing.assert_array_equal(getattr(h, field), getattr(g, field), err_msg=field)
    assert np.load(tmp_path / "s" / "color.npy").dtype == np.uint8


def test_ply_and_back_within_float32(tmp_path):
    """Folder -> PLY -> folder and PLY -> folder -> PLY keep every value within float32 rounding."""
    g = scene_gaussians(degree=1)
    save_scenesplat(tmp_path / "a", g)
    qr_cl.save_ply(tmp_path / "a.ply", load_scene(tmp_path / "a"))
    save_scenesplat(tmp_path / "b", qr_cl.load_ply(tmp_path / "a.ply"))
    back = SceneSplatFolder(tmp_path / "b").gaussians
    for field in ("means", "sh"):
        np.testing.assert_array_equal(getattr(back, field), getattr(g, field), err_msg=field)
    for field in ("quats", "scales", "opacities"):
        np.testing.assert_allclose(getattr(back, field), getattr(g, field), rtol=2e-6, atol=1e-7, err_msg=field)
    np.testing.assert_array_equal(np.load(tmp_path / "b" / "color.npy"), np.load(tmp_path / "a" / "color.npy"))


def test_uint8_and_float_colours_give_the_same_dc(tmp_path):
    g = scene_gaussians()
    scenesplat_files(tmp_path / "u", g)
    colour = np.load(tmp_path / "u" / "color.npy")
    scenesplat_files(tmp_path / "f", g, color=(colour / 255.0).astype(np.float32))
    a, b = load_scene(tmp_path / "u"), load_scene(tmp_path / "f")
    np.testing.assert_allclose(a.sh, b.sh, atol=1e-6)
    assert a.sh_degree == 0
    np.testing.assert_allclose(a.rgb, colour / 255.0, atol=1e-6)
    np.testing.assert_allclose(a.opacities, g.opacities)         # [N,1] read as [N]


def test_folder_renders_the_pixels_of_its_ply(tmp_path):
    """The folder and the PLY written from its Gaussians render the same pixels, on the folder's
    own frames (nerfstudio transforms_train.json) and on orbit cameras."""
    means, quats, scales, opacities, viewmat, K, w, h = make_random_scene(400, seed=3)
    g = scene_gaussians(400, seed=3)
    scenesplat_files(tmp_path / "s", g)
    c2w = np.eye(4)
    c2w[:3, :3] = np.diag([1.0, -1.0, -1.0])          # OpenGL camera looking down +z of the world
    frames = [{"file_path": "images/frame_000.jpg", "transform_matrix": c2w.tolist()},
              {"file_path": "images/frame_001.jpg", "transform_matrix": (c2w + np.diag([0, 0, 0, 0])).tolist(),
               "fl_x": 50.0}]
    (tmp_path / "s" / "transforms_train.json").write_text(json.dumps(
        {"fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
         "w": w, "h": h, "frames": frames}))
    folder = load_scene(tmp_path / "s")
    qr_cl.save_ply(tmp_path / "s.ply", folder)
    ply = qr_cl.load_ply(tmp_path / "s.ply")
    cams = load_cameras(tmp_path / "s" / "transforms_train.json")
    assert [c.name for c in cams] == ["images/frame_000.jpg", "images/frame_001.jpg"] and cams[1].fx == 50.0
    np.testing.assert_allclose(cams[0].viewmat, viewmat, atol=1e-7)
    for cam in cams + orbit_cameras(folder.means, 2, 48, 36):
        images = [render_volume_fused(s.means, s.quats, s.scales, s.opacities, s.sh, cam.viewmat, cam.K,
                                      cam.width, cam.height, sh_degree=0)[0].numpy() for s in (folder, ply)]
        assert images[0].max() > 0.1
        np.testing.assert_allclose(images[0], images[1], atol=2e-5)
        np.testing.assert_array_equal(*(np.round(255 * np.clip(im, 0, 1)).astype(np.uint8) for im in images))


def test_labels_and_features_are_read_when_asked(tmp_path):
    g = scene_gaussians(50)
    seg = np.arange(50) % 21 - 1
    scenesplat_files(tmp_path / "s", g, segment20=seg[:, None].astype(np.int32), instance=seg.astype(np.int16),
                     lang_feat=np.ones((50, 8), np.float16), valid_feat_mask=(seg >= 0).astype(np.uint8))
    folder = SceneSplatFolder(tmp_path / "s")
    np.testing.assert_array_equal(folder.labels("segment20"), seg)
    assert folder.labels("instance").dtype == np.int64
    feats, valid = folder.language_features()
    assert feats.shape == (50, 8) and feats.dtype == np.float32 and valid.sum() == (seg >= 0).sum()
    (tmp_path / "s" / "segment20.npy").unlink()                 # read once: already in memory
    np.testing.assert_array_equal(folder.labels("segment20"), seg)


def _break(folder, name, value):
    np.save(folder / f"{name}.npy", value)


HOSTILE = {
    "nan coordinate": (lambda g: ("coord", np.where(np.arange(len(g))[:, None] == 7, np.nan, g.means)),
                       r"coord\.npy: 1 rows hold NaN or infinite values \(first: row 7\)"),
    "wrong shape": (lambda g: ("scale", g.scales[:, :2]), r"scale\.npy: shape \[40, 2\], expected \[N, 3\]"),
    "row count": (lambda g: ("quat", g.quats[:-1]), r"quat\.npy: 39 rows, but coord\.npy has 40"),
    "colour 0-255 as float": (lambda g: ("color", np.full((len(g), 3), 200.0, np.float32)),
                              r"color\.npy: float32 colours range over \[200, 200\]; expected uint8 0-255 or float 0-1"),
    "colour as int16": (lambda g: ("color", np.full((len(g), 3), 20, np.int16)),
                        r"color\.npy: dtype int16; expected uint8 0-255 or float 0-1 colours"),
    "opacity logits": (lambda g: ("opacity", g.opacities * 8 - 4), r"opacity\.npy: opacities range over"),
    "log scales": (lambda g: ("scale", np.log(g.scales)), r"scale\.npy: negative scales"),
    "zero quaternion": (lambda g: ("quat", np.where(np.arange(len(g))[:, None] == 3, 0.0, g.quats)),
                        r"quat\.npy: 1 zero quaternions \(first: row 3\)"),
    "x,y,z,w order": (lambda g: ("quat", np.roll(g.quats * np.sign(g.quats[:, :1]), -1, axis=1)),
                      r"quat\.npy: .* x,y,z,w order\?"),
    "not an array": (lambda g: ("opacity", None), r"opacity\.npy: not a readable \.npy array"),
}


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_hostile_folders_name_the_file_and_the_problem(tmp_path, case):
    g = scene_gaussians(40, seed=1)
    scenesplat_files(tmp_path / "s", g)
    make, message = HOSTILE[case]
    name, value = make(g)
    if value is None:
        (tmp_path / "s" / f"{name}.npy").write_bytes(b"\x93NUMPY broken")
    else:
        _break(tmp_path / "s", name, value)
    with pytest.raises(SceneFormatError, match=message):
        load_scene(tmp_path / "s")


def test_missing_files_and_bad_labels(tmp_path):
    g = scene_gaussians(40)
    scenesplat_files(tmp_path / "s", g, segment20=np.full(40, 2.5), segment200=np.full(40, -3), instance=np.ones((40, 2)))
    folder = SceneSplatFolder(tmp_path / "s")
    with pytest.raises(SceneFormatError, match=r"segment20\.npy: labels must be integers"):
        folder.labels("segment20")
    with pytest.raises(SceneFormatError, match=r"segment200\.npy: label -3 is below the ignore index -1"):
        folder.labels("segment200")
    with pytest.raises(SceneFormatError, match=r"instance\.npy: shape \[40, 2\], expected \[N\]"):
        folder.labels("instance")
    with pytest.raises(SceneFormatError, match=r"lang_feat\.npy: no such file"):
        folder.language_features()
    (tmp_path / "s" / "opacity.npy").unlink()
    with pytest.raises(SceneFormatError, match=r"not a SceneSplat folder, missing opacity\.npy"):
        load_scene(tmp_path / "s")
    (tmp_path / "empty").mkdir()
    with pytest.raises(SceneFormatError, match=r"empty: a folder with neither point_cloud\.ply nor SceneSplat's"):
        load_scene(tmp_path / "empty")


def test_convert_and_render_commands(tmp_path, capsys):
    from qr_cl.app.cli import main

    g = scene_gaussians(60, degree=1)
    save_scenesplat(tmp_path / "s", g, {"segment20": np.zeros(60, np.int32)})
    assert main(["convert", str(tmp_path / "s"), str(tmp_path / "s.ply")]) == 0
    out = capsys.readouterr().out
    assert "not in the PLY (kept in" in out and "segment20" in out and "wrote 60 Gaussians (SH degree 1)" in out
    assert main(["convert", str(tmp_path / "s.ply"), str(tmp_path / "t")]) == 0
    np.testing.assert_array_equal(load_scene(tmp_path / "t").sh, g.sh)
    with pytest.raises(SystemExit, match="exists"):
        main(["convert", str(tmp_path / "s.ply"), str(tmp_path / "t")])
    assert main(["render", str(tmp_path / "t"), "--orbit", "1", "--width", "32", "--height", "24",
                 "--out", str(tmp_path / "r")]) == 0
    coord = np.load(tmp_path / "t" / "coord.npy")
    coord[5, 1] = np.nan
    np.save(tmp_path / "t" / "coord.npy", coord)
    capsys.readouterr()
    assert main(["render", str(tmp_path / "t"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "coord.npy: 1 rows hold NaN" in err[0] and "Traceback" not in err[0]
