"""The synthetic labelled-room generator: determinism, caching, the format, simulated CLIP."""
from __future__ import annotations

import filecmp
import json

import numpy as np
import pytest

from qr_cl.app.evaluation.metrics import NYU40_NAMES
from qr_cl.app.scenes.folders import load_scene_folder
from qr_cl.app.scenes.synthetic import room_folder
from tests.synthetic_helpers import tiny_config


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return room_folder(tiny_config(3), tmp_path_factory.mktemp("cache"))


def test_same_seed_same_files_and_cache_reused(scene, tmp_path):
    again = room_folder(tiny_config(3), tmp_path)
    for rel in ("point_cloud.ply", "cameras.json", "classes.json", "labels/points.ply",
                "labels/gaussian_labels.npy", "language_features/frame_000_s.npy",
                "language_features/frame_002_f.npy"):
        assert filecmp.cmp(scene / rel, again / rel, shallow=False), rel
    mtime = (again / "point_cloud.ply").stat().st_mtime_ns
    assert room_folder(tiny_config(3), tmp_path) == again
    assert (again / "point_cloud.ply").stat().st_mtime_ns == mtime
    other = room_folder(tiny_config(4), tmp_path)
    assert not filecmp.cmp(scene / "point_cloud.ply", other / "point_cloud.ply", shallow=False)


def test_folder_loads_and_masks_match_classes(scene):
    data = load_scene_folder(scene)
    cfg = tiny_config(3)
    assert len(data.gaussians) == cfg.n_gaussians and len(data.frames) == cfg.n_views
    assert data.feature_dim == cfg.dim
    assert set(data.classes.ids.tolist()) == set(NYU40_NAMES)
    assert data.gaussian_labels.shape == (cfg.n_gaussians,)
    assert (data.gaussian_labels == -1).sum() > 0          # floaters
    assert set(np.unique(data.point_labels)) <= set(data.gaussian_labels.tolist())
    for frame in data.frames:
        assert frame.masks.shape == (cfg.height, cfg.width)
        assert (frame.masks >= 0).mean() > 0.5
        assert np.allclose(np.linalg.norm(frame.features, axis=1), 1, atol=1e-5)


def test_orthogonal_prototype_masks_name_a_class_in_the_room(tmp_path):
    """The rooms of earlier releases: random prototypes, each mask feature nearest (among the
    text features) to a class present in the scene."""
    data = load_scene_folder(room_folder(tiny_config(3, features="orthogonal"), tmp_path))
    present = set(np.unique(data.gaussian_labels[data.gaussian_labels >= 0]).tolist())
    hits = 0
    for frame in data.frames:
        best = data.classes.ids[(frame.features @ data.classes.text_features.T).argmax(1)]
        hits += sum(int(b) in present for b in best)
    assert hits >= 0.8 * sum(len(f.features) for f in data.frames)


def test_cameras_are_inside_the_room(scene):
    cams = json.loads((scene / "cameras.json").read_text())
    w, d, h = tiny_config(3).room_size
    for c in cams:
        x, y, z = c["position"]
        assert 0 < x < w and 0 < y < d and 0 < z < h
