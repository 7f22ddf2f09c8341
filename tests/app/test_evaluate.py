"""Evaluation: metrics on a hand-made case with known IoU, App. B pseudo labels, the eval command."""
from __future__ import annotations

import json

import numpy as np
import pytest

from qr_cl.app.cli import main
from qr_cl.app.evaluation.labels import ground_truth, pseudo_labels, reached_gaussians
from qr_cl.app.evaluation.metrics import confusion_matrix, miou_macc
from qr_cl.app.evaluation.scoring import evaluate_features
from qr_cl.app.scenes.folders import load_scene_folder
from qr_cl.app.scenes.room_features import RoomFeatures
from qr_cl.app.training.rays import view_plan
from qr_cl.scene import Gaussians
from qr_cl.stages import select
from tests.synthetic_helpers import tiny_config, tiny_scene


def test_known_iou_and_acc():
    gt = np.array([1, 1, 1, 2, 2, -1, 7])
    pred = np.array([1, 1, 2, 2, 1, 1, 3])
    # class 1: TP 2, FP 1, FN 1 -> IoU 2/4, Acc 2/3; class 2: TP 1, FP 1, FN 1 -> IoU 1/3, Acc 1/2;
    # class 3 is absent from the ground truth; gt -1 and the unlisted 7 are ignored.
    res = miou_macc(pred, gt, (1, 2, 3))
    assert res["miou"] == pytest.approx((1 / 2 + 1 / 3) / 2)
    assert res["macc"] == pytest.approx((2 / 3 + 1 / 2) / 2)
    assert set(res["per_class"]) == {1, 2} and res["n_evaluated"] == 5
    assert confusion_matrix(pred, gt, (1, 2, 3)).tolist() == [[2, 1, 0], [1, 1, 0], [0, 0, 0]]
    perfect = miou_macc(gt[:5], gt[:5], (1, 2))
    assert perfect["miou"] == perfect["macc"] == 1.0
    with pytest.raises(ValueError, match="outside the evaluated classes"):
        miou_macc(np.array([9]), np.array([1]), (1, 2))


def _gaussians(means, scales, opacities):
    n = len(means)
    return Gaussians(np.asarray(means, np.float32), np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
                     np.asarray(scales, np.float32), np.asarray(opacities, np.float32), np.zeros((n, 1, 3), np.float32))


def test_pseudo_labels_app_b():
    points = np.array([[0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [-0.01, 0, 0], [0, 0.01, 0],
                       [5, 5, 5], [5.01, 5, 5]], np.float64)
    labels = np.array([3, 3, 4, 3, 4, 9, 9])
    g = _gaussians([[0, 0, 0], [0, 0, 0], [2, 2, 2], [5, 5, 5], [0.05, 0, 0]],
                   [[1, 1, 1], [1, 1, 1], [0.1, 0.1, 0.1], [0.1, 0.1, 0.1], [0.1, 0.1, 0.001]],
                   [0.9, 0.05, 0.9, 0.9, 0.9])
    out = pseudo_labels(g, points, labels, k=5, max_mahalanobis=0.1)
    # 0: majority of its 5 neighbours (3, 3, 3, 4, 4) -> 3; 1: opacity < 0.1 -> dropped;
    # 2: a floater, every neighbour > 0.1 Mahalanobis away -> dropped; 3: on the 9 points -> 9;
    # 4: 3 cm from the nearest point along x but sigma_x = 0.1: Mahalanobis 0.3 -> dropped.
    assert out.tolist() == [3, -1, -1, 9, -1]
    wide = pseudo_labels(g, points, labels, k=5, max_mahalanobis=0.5)
    assert wide[4] in (3, 4)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return tiny_scene(tmp_path_factory.mktemp("cache"), seed=2)


def test_oracle_features_score_high_random_low(scene):
    data = load_scene_folder(scene)
    gt, source = ground_truth(data)
    assert source == "points" and 0.2 < (gt >= 0).mean() < 1
    truth = data.gaussian_labels
    agree = gt[gt >= 0] == truth[gt >= 0]
    assert agree.mean() > 0.9
    protos = RoomFeatures(tiny_config()).text()
    oracle = np.stack([protos[max(int(c), 1)] for c in truth]).astype(np.float32)
    good = evaluate_features(data, oracle, gt)
    rand = evaluate_features(data, np.random.default_rng(0).standard_normal(oracle.shape).astype(np.float32), gt)
    for size in (19, 15, 10):
        assert good[size]["miou"] > 0.7 and rand[size]["miou"] < 0.3
    gt_only, src = ground_truth(data, "gaussians")
    assert src == "gaussians" and evaluate_features(data, oracle, gt_only)[19]["miou"] > 0.95


def test_reached_gaussians_are_those_some_pixel_selects(scene):
    data = load_scene_folder(scene)
    reached = reached_gaussians(data, "quantile", 4)
    expected = np.zeros(len(data.gaussians), bool)
    for view in range(len(data.frames)):
        ids = select(view_plan(data, view), "quantile", 4).host()["ids"]
        expected[ids[ids >= 0]] = True
    assert np.array_equal(reached, expected)
    assert 0 < reached.mean() < 1
    more = reached_gaussians(data, "volume", 0)        # every Gaussian a ray blends holds K's choices
    assert np.all(more[reached]) and more.sum() > reached.sum()
    g = data.gaussians                                   # a Gaussian without opacity is never reached
    hidden = int(np.flatnonzero(more)[0])
    data.gaussians = Gaussians(g.means, g.quats, g.scales, np.where(np.arange(len(g.means)) == hidden, 0,
                                                                    g.opacities).astype(np.float32), g.sh)
    assert not reached_gaussians(data, "volume", 0)[hidden]


def test_eval_command_writes_tables_images_and_ply(scene, tmp_path, capsys):
    import open3d as o3d
    data = load_scene_folder(scene)
    protos = RoomFeatures(tiny_config()).text()
    np.save(tmp_path / "f.npy", np.stack([protos[max(int(c), 1)] for c in data.gaussian_labels]).astype(np.float32))
    out = tmp_path / "eval"
    assert main(["eval", str(scene), "--features", str(tmp_path / "f.npy"), "--out", str(out), "--views", "0", "1"]) == 0
    res = json.loads((out / "results.json").read_text())
    assert res["scenes"][0]["metrics"]["19"]["miou"] > 0.7
    assert "mIoU19" in (out / "results.md").read_text() and "results.md" in capsys.readouterr().out
    picture = out / "images" / f"{scene.name}_{data.frames[1].camera.name}.png"
    assert picture.is_file() and data.frames[1].camera.name
    from PIL import Image
    assert Image.open(picture).size[0] >= 5 * 320          # five panels of at least 320x240
    cloud = o3d.io.read_point_cloud(str(out / "images" / f"{scene.name}_segmentation.ply"))
    assert len(cloud.points) == len(data.gaussians) and cloud.has_colors()


def test_tiny_demo_writes_the_report(tmp_path, capsys):
    args = ["demo", "--out", str(tmp_path / "demo"), "--cache", str(tmp_path / "cache"), "--train-scenes", "1",
            "--gaussians", "6000", "--steps", "3", "--short-steps", "2", "--rays", "64", "--views", "1"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "Report:" in out
    report = (tmp_path / "demo" / "report.md").read_text()
    for method in ("Q-Render K=40", "Q-Render K=5", "top-K K=40", "top-K K=5", "V-Render", "free features",
                   "Dr.Splat registration", "GS-Net overfit", "GS-Net generalised"):
        assert method in report, method
    assert "per-scene baseline" not in report
    assert "held-out" in report and "training" in report
    assert "3dgs style" in out and any(p.name.startswith("splat-room-") for p in (tmp_path / "cache").iterdir())
    compared = report.split("## Renderers compared")[1].split("##")[0]
    assert sum(line.startswith("| ") for line in compared.splitlines()) == 7       # header, rule, 5 renderers
    table2 = report.split("## Table 2")[1].split("##")[0]
    assert sum(line.startswith("| ") for line in table2.splitlines()) == 2 + 4 + 3 + 2  # 4 rows, 3 paper rows, 2 more
    assert "| *paper* | *23.21* |" in table2 and "labelled ones keep no feature" in table2
    res = json.loads((tmp_path / "demo" / "results.json").read_text())
    assert len(res["rows"]) == 15 and all(0 <= r["metrics"]["19"]["macc"] <= 1 for r in res["rows"])
    assert 0 < res["registration"]["reached"] <= res["registration"]["gaussians"]
    assert [r["split"] for r in res["rows"][-3:]] == ["held-out"] * 3              # per-scene methods: held-out only
    assert len(list((tmp_path / "demo" / "images" / "compared").glob("*_compared.png"))) == 2
    assert all(0 <= r["reached"]["macc"] <= 1 for r in res["rows"])
    assert (tmp_path / "demo" / "runs" / "gsnet-q40" / "checkpoint.pt").is_file()


def test_eval_refuses_an_unknown_query_before_any_work(scene, tmp_path):
    data = load_scene_folder(scene)
    np.save(tmp_path / "f.npy", np.zeros((len(data.gaussians), data.feature_dim), np.float32))
    with pytest.raises(SystemExit, match="'tabel' is not a class of .*classes.json.*closest: table"):
        main(["eval", str(scene), "--features", str(tmp_path / "f.npy"), "--out", str(tmp_path / "o"),
              "--query", "tabel"])
    assert not (tmp_path / "o" / "images").exists()
