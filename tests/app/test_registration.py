"""Dr.Splat's registration (qr_cl.app.registration): the top contributors against gsplat's query,
the kernel path against its float64 twin on a tiny room, streaming and chunking, the unlabelled
Gaussians in the evaluation, and ``qr-cl register``."""
from __future__ import annotations

import json

import numpy as np
import pytest

from qr_cl.app.cli import main
from qr_cl.app.evaluation.metrics import UNLABELLED, miou_macc
from qr_cl.app.evaluation.scoring import predict
from qr_cl.app.registration.contributors import top_contributors
from qr_cl.app.registration.register import ViewMasks, register, scene_views
from qr_cl.app.training.rays import camera_plan
from qr_cl.app.scenes.folders import load_scene_folder
from tests.app import register_twin
from tests.render.test_top_contributors import meta_of, query


@pytest.fixture(scope="module")
def levels(tiny_room):
    """The tiny room loaded at each of its four mask levels."""
    return [load_scene_folder(tiny_room, level) for level in range(4)]


def _twin(scene, views, k):
    metas = [camera_plan(scene.gaussians, v.camera).meta() for v in views]
    return register_twin.register(metas, views, len(scene.gaussians), k)


def test_contributors_are_gsplats_top_contributors(random_scene):
    meta = meta_of(random_scene, packed=False)
    plan = meta["selections"][0].plan
    w, h = meta["width"], meta["height"]
    pixels = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2).astype(np.int32)
    for k in (3, 40):
        ids, weights = top_contributors(plan, pixels, k)
        want_ids, want_w = (t[0].reshape(-1, k).numpy() for t in query(meta, k=k))
        np.testing.assert_array_equal(ids, want_ids)
        np.testing.assert_array_equal(weights, want_w)
    with pytest.raises(ValueError, match="k=0"):
        top_contributors(plan, pixels, 0)


@pytest.mark.parametrize("k", [3, 40])
def test_registration_equals_the_float64_twin(levels, k):
    scene = levels[0]
    views = list(scene_views([scene]))
    got = register(scene.gaussians, iter(views), k=k, progress=False)
    want, want_weight = _twin(scene, views, k)
    assert got.features.dtype == np.float32 and got.features.shape == want.shape
    assert np.abs(got.features - want).max() <= 1e-5
    np.testing.assert_allclose(got.weight, want_weight, rtol=1e-5, atol=1e-7)
    assert np.array_equal(got.reached, want_weight > 0)
    assert 0.2 < got.reached.mean() < 1.0                      # some Gaussians are never picked ...
    assert not got.features[~got.reached].any()                # ... and keep no feature
    np.testing.assert_allclose(np.linalg.norm(got.features[got.reached], axis=1), 1.0, atol=1e-5)
    assert got.views == len(views) and got.rays == sum(int((v.masks >= 0).any(0).sum()) for v in views)
    assert 0 < got.entries <= k * got.rays


def test_every_level_equals_the_twin_and_differs_from_one(levels):
    views = list(scene_views(levels))
    assert views[0].masks.shape[0] == 4 and len(views[0].features) == sum(len(s.frames[0].features) for s in levels)
    got = register(levels[0].gaussians, views, k=10, progress=False)
    want, _ = _twin(levels[0], views, 10)
    assert np.abs(got.features - want).max() <= 1e-5
    one = register(levels[0].gaussians, scene_views(levels[:1]), k=10, progress=False)
    assert np.array_equal(one.reached, got.reached) and np.abs(one.features - got.features).max() > 0.1


def test_chunks_of_rays_give_the_same_features(levels):
    scene = levels[0]
    whole = register(scene.gaussians, scene_views([scene]), k=8, progress=False)
    chunked = register(scene.gaussians, scene_views([scene]), k=8, chunk_rays=500, progress=False)
    assert np.abs(whole.features - chunked.features).max() <= 1e-6
    assert (whole.rays, whole.entries) == (chunked.rays, chunked.entries)


def test_views_stream_one_at_a_time(levels):
    """register consumes a generator view by view: a view is made only once the last is registered."""
    scene, made = levels[0], []

    def views():
        for view in scene_views([scene]):
            made.append(view.name)
            yield view
    result = register(scene.gaussians, views(), k=5, progress=False)
    assert result.views == len(made) == len(scene.frames)


def test_bad_views_are_refused(levels):
    scene = levels[0]
    view = next(scene_views([scene]))
    with pytest.raises(ValueError, match="do not match"):
        register(scene.gaussians, [ViewMasks(view.name, view.camera, view.masks[0], view.features)], progress=False)
    with pytest.raises(ValueError, match="no views"):
        register(scene.gaussians, [], progress=False)


def test_gaussians_without_a_feature_are_scored_unlabelled(levels):
    table = levels[0].classes
    features = np.stack([table.text_features[0], np.zeros_like(table.text_features[0]), table.text_features[1]])
    pred = predict(features, table)
    assert pred.tolist() == [table.ids[0], UNLABELLED, table.ids[1]]
    gt = np.array([table.ids[0], table.ids[0], table.ids[1]])
    scores = miou_macc(pred, gt, table.ids[:2])
    assert scores["per_class"][int(table.ids[0])] == {"iou": 0.5, "acc": 0.5, "support": 2}
    assert scores["per_class"][int(table.ids[1])]["iou"] == 1.0 and scores["unlabelled"] == 1
    with pytest.raises(ValueError, match="outside"):
        miou_macc(np.array([-2, 1, 1]), gt, table.ids[:2])


def test_register_command_writes_features_that_eval_reads(tiny_room, tmp_path, capsys):
    out = tmp_path / "reg"
    assert main(["register", str(tiny_room), "--out", str(out), "-k", "10", "--levels", "all"]) == 0
    features = np.load(out / "features.npy")
    summary = json.loads((out / "registration.json").read_text())
    scene = load_scene_folder(tiny_room)
    assert features.shape == (len(scene.gaussians), scene.feature_dim) and summary["k"] == 10
    assert summary["levels"] == [0, 1, 2, 3]
    assert summary["reached"] == int((np.linalg.norm(features, axis=1) > 0).sum())
    assert "mIoU19" in capsys.readouterr().out                   # the room has ground truth: scored
    assert main(["eval", str(tiny_room), "--features", str(out / "features.npy"), "--out", str(tmp_path / "ev")]) == 0
    assert main(["register", str(tmp_path / "missing"), "--out", str(out)]) == 2
