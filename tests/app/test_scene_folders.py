"""Scene folder loading: a valid folder loads; each kind of corruption names file, frame, problem."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from qr_cl.app.scenes.folders import SceneDataError, load_scene_folder, read_labelled_points
from qr_cl.app.scenes.synthetic import room_folder, write_labelled_points
from tests.synthetic_helpers import tiny_config


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    return room_folder(tiny_config(5), tmp_path_factory.mktemp("cache"))


@pytest.fixture
def scene(source, tmp_path):
    dst = tmp_path / "scene"
    shutil.copytree(source, dst)
    return dst


def test_loads_level_and_resized_masks(scene):
    data = load_scene_folder(scene, level=2)
    assert data.frames[0].masks.dtype == np.int32
    s = np.load(scene / "language_features/frame_001_s.npy")
    big = np.repeat(np.repeat(s, 2, axis=1), 2, axis=2)
    np.save(scene / "language_features/frame_001_s.npy", big.astype(np.float32))
    frame = load_scene_folder(scene).frames[1]
    assert frame.masks.shape == big.shape[1:]
    assert frame.camera.width == big.shape[2] and frame.camera.fx == pytest.approx(2 * data.frames[1].camera.fx)


@pytest.mark.parametrize("corrupt, words", [
    (lambda d: np.save(d / "language_features/frame_002_s.npy",
                       np.full((4, 48, 64), 99, np.int32)), ["frame_002_s.npy", "frame_002", "[99, 99]"]),
    (lambda d: np.save(d / "language_features/frame_001_s.npy",
                       np.zeros((4, 50, 50), np.int32)), ["frame_001_s.npy", "50x50", "aspect"]),
    (lambda d: np.save(d / "language_features/frame_003_f.npy",
                       np.ones((30, 7), np.float32)), ["language_features", "disagree", "frame_003"]),
    (lambda d: (d / "language_features/frame_000_f.npy").unlink(), ["frame_000_f.npy", "missing"]),
    (lambda d: np.save(d / "labels/gaussian_labels.npy", np.zeros(5, np.int32)), ["gaussian_labels.npy", "3000"]),
    (lambda d: np.save(d / "language_features/frame_000_s.npy", np.full((4, 48, 64), 0.5)),
     ["frame_000_s.npy", "integers"]),
])
def test_bad_input_is_named(scene, corrupt, words):
    corrupt(scene)
    with pytest.raises(SceneDataError) as err:
        load_scene_folder(scene)
    for w in words:
        assert w in str(err.value), (w, str(err.value))


def test_class_text_dim_mismatch(scene):
    data = json.loads((scene / "classes.json").read_text())
    data["classes"][3]["text_feature"] = [0.0] * 7
    (scene / "classes.json").write_text(json.dumps(data))
    with pytest.raises(SceneDataError, match=r"classes.json.*'bed'.*32-D"):
        load_scene_folder(scene)


def test_level_out_of_range(scene):
    with pytest.raises(SceneDataError, match="level 4 requested, the file has 4 levels"):
        load_scene_folder(scene, level=4)


def test_labelled_points_round_trip(tmp_path):
    pts = np.random.default_rng(0).random((10, 3))
    write_labelled_points(tmp_path / "p.ply", pts, np.arange(10))
    got, labels = read_labelled_points(tmp_path / "p.ply")
    assert np.allclose(got, pts, atol=1e-6) and labels.tolist() == list(range(10))
    (tmp_path / "q.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n"
                                     b"property float y\nproperty float z\nend_header\n0 0 0\n")
    with pytest.raises(SceneDataError, match=r"q.ply.*\['label'\]"):
        read_labelled_points(tmp_path / "q.ply")


def test_langsplat_levels_keep_only_their_own_rows(scene):
    """LangSplat stacks the features of its four levels in _f.npy and offsets level j's ids by the
    mask counts of the levels before it: a frame keeps the chosen level's rows, re-indexed, so
    the same object's masks at other levels are never negatives of the loss."""
    counts = [3, 2, 4, 1]                               # masks per level, uneven
    seg = np.full((4, 48, 64), -1, np.int32)
    for j, c in enumerate(counts):
        for m in range(c):
            seg[j, :, m * 64 // c:(m + 1) * 64 // c - 1] = sum(counts[:j]) + m
    feats = np.random.default_rng(0).normal(size=(sum(counts), 32)).astype(np.float32)
    np.save(scene / "language_features/frame_000_s.npy", seg)
    np.save(scene / "language_features/frame_000_f.npy", feats)
    unit = feats / np.linalg.norm(feats, axis=1, keepdims=True)
    for level, c in enumerate(counts):
        frame = load_scene_folder(scene, level=level).frames[0]
        start = sum(counts[:level])
        assert frame.features.shape == (c, 32)
        np.testing.assert_allclose(frame.features, unit[start:start + c], rtol=1e-6)
        np.testing.assert_array_equal(frame.masks, np.where(seg[level] >= 0, seg[level] - start, -1))


def test_synthetic_scenes_are_written_the_langsplat_way(source):
    """Four levels with per-level offsets and a distinct feature for each level's mask."""
    seg = np.load(source / "language_features/frame_000_s.npy")
    feats = np.load(source / "language_features/frame_000_f.npy")
    masks = int(seg[0].max()) + 1
    assert seg.shape[0] == 4 and len(feats) == 4 * masks
    for j in range(4):
        np.testing.assert_array_equal(seg[j], np.where(seg[0] >= 0, seg[0] + j * masks, -1))
    assert not np.allclose(feats[:masks], feats[masks:2 * masks])
    frame = load_scene_folder(source, level=3).frames[0]
    assert len(frame.features) == masks and frame.masks.max() == masks - 1
