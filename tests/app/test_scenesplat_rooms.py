"""SceneSplat folders made from the procedural rooms: labels in each id space as ground truth,
frames from transforms_train.json, training, queries and one-line errors for damaged folders."""
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from qr_cl.app.cli import main
from qr_cl.app.evaluation.labels import ground_truth
from qr_cl.app.evaluation.scoring import evaluate_features
from qr_cl.app.query.scene import load_query_scene
from qr_cl.app.scenes.folders import load_scene_folder
from qr_cl.app.scenes.label_spaces import SCANNET20_NYU40, SCANNET200_NYU40
from qr_cl.scene import Camera, save_scenesplat
from qr_cl.scene.scenesplat import IGNORE_LABEL

#: NYU40 id -> the first id of each ScanNet space that maps onto it (-1: none).
FROM_NYU40 = {"segment20": {n: i for i, n in reversed(list(enumerate(SCANNET20_NYU40)))},
              "segment200": {n: i for i, (_, n) in reversed(list(enumerate(SCANNET200_NYU40)))}}


def transforms(cameras: list[Camera]) -> dict:
    """nerfstudio transforms of ``cameras`` (OpenGL camera-to-world, shared intrinsics)."""
    frames = []
    for cam in cameras:
        c2w = np.linalg.inv(cam.viewmat.astype(np.float64)) @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": f"images/{cam.name}.jpg", "transform_matrix": c2w.tolist()})
    c = cameras[0]
    return {"fl_x": c.fx, "fl_y": c.fy, "cx": c.cx, "cy": c.cy, "w": c.width, "h": c.height, "frames": frames}


def scenesplat_room(room: Path, out: Path, label_file: str | None) -> Path:
    """The room folder ``room`` as a SceneSplat folder: its Gaussians as .npy files, its NYU40
    labels in ``label_file``'s space (``None``: as labels/gaussian_labels.npy), instance ids, its
    frames as transforms_train.json, and its language features and classes.json."""
    data = load_scene_folder(room)
    extra = {"instance": np.arange(len(data.gaussians)) % 7 - 1}
    if label_file is not None:
        table = FROM_NYU40[label_file]
        extra[label_file] = np.array([table.get(int(c), IGNORE_LABEL) for c in data.gaussian_labels], np.int16)
    save_scenesplat(out, data.gaussians, extra)
    (out / "sh.npy").unlink()                                  # SceneSplat's own files only
    if label_file is None:
        shutil.copytree(room / "labels", out / "labels", ignore=shutil.ignore_patterns("points.ply"))
    (out / "transforms_train.json").write_text(json.dumps(transforms([f.camera for f in data.frames])))
    shutil.copytree(room / "language_features", out / "language_features")
    shutil.copy(room / "classes.json", out / "classes.json")
    return out


@pytest.mark.parametrize("label_file", ["segment20", "segment200", None])
def test_labels_in_every_space_score_100_when_features_name_them(tiny_room, tmp_path, label_file):
    folder = scenesplat_room(tiny_room, tmp_path / "s", label_file)
    scene = load_scene_folder(folder)
    gt, source = ground_truth(scene, "gaussians")
    assert source == "gaussians" and (gt >= 1).sum() > 100
    rows = {int(c): i for i, c in enumerate(scene.classes.ids)}
    named = np.stack([scene.classes.text_features[rows.get(int(c), 0)] for c in gt])
    metrics = evaluate_features(scene, named, gt)
    assert metrics[19]["miou"] == pytest.approx(1.0)
    assert np.array_equal(scene.instances, np.arange(len(gt)) % 7 - 1)
    wrong = named[np.random.default_rng(0).permutation(len(named))]   # the test can fail: shuffled rows
    assert evaluate_features(scene, wrong, gt)[19]["miou"] < 0.9


def test_frames_come_from_transforms_train(tiny_room, tmp_path):
    room, folder = load_scene_folder(tiny_room), load_scene_folder(scenesplat_room(tiny_room, tmp_path / "s", "segment20"))
    assert [f.name for f in folder.frames] == [f.name for f in room.frames]
    for a, b in zip(room.frames, folder.frames):
        np.testing.assert_allclose(b.camera.viewmat, a.camera.viewmat, atol=1e-5)
        assert (b.camera.fx, b.camera.width, b.camera.height) == (a.camera.fx, a.camera.width, a.camera.height)
        np.testing.assert_array_equal(b.masks, a.masks)
    np.testing.assert_allclose(folder.gaussians.rgb, room.gaussians.rgb, atol=0.5 / 255 + 1e-6)


def test_train_eval_register_and_query_open_a_folder(tiny_room, tmp_path, capsys):
    folder = scenesplat_room(tiny_room, tmp_path / "s", "segment200")
    assert main(["train", str(folder), "--out", str(tmp_path / "run"), "--steps", "2", "--views", "1", "--rays", "64",
                 "--net", "tiny"]) == 0
    assert main(["eval", str(folder), "--checkpoint", str(tmp_path / "run" / "checkpoint.pt"), "--gt", "gaussians",
                 "--out", str(tmp_path / "eval")]) == 0
    assert "mIoU19" in (tmp_path / "eval" / "results.md").read_text()
    assert main(["register", str(folder), "--out", str(tmp_path / "reg")]) == 0
    assert np.load(tmp_path / "reg" / "features.npy").shape[0] == len(np.load(folder / "coord.npy"))
    asked = load_query_scene(folder)
    assert len(asked.cameras) == len(asked.data.frames) > 0 and asked.classes is not None


DAMAGE = {
    "nan coordinates": (lambda f: np.save(f / "coord.npy", np.full((len(np.load(f / "coord.npy")), 3), np.nan,
                                                                   np.float32)), r"coord\.npy: .* NaN"),
    "wrong shape": (lambda f: np.save(f / "scale.npy", np.load(f / "scale.npy")[:, :2]), r"scale\.npy: shape"),
    "missing file": (lambda f: (f / "quat.npy").unlink(), r"missing quat\.npy"),
    "colours 0-255 as float": (lambda f: np.save(f / "color.npy", np.load(f / "color.npy").astype(np.float32)),
                               r"color\.npy: float32 colours range over .* expected uint8 0-255 or float 0-1"),
    "label outside its space": (lambda f: np.save(f / "segment20.npy", np.full(len(np.load(f / "coord.npy")), 20,
                                                                               np.int16)),
                                r"segment20\.npy: scannet20 labels: .* outside the space"),
}


@pytest.mark.parametrize("case", sorted(DAMAGE))
@pytest.mark.parametrize("command", ["train", "eval"])
def test_damaged_folders_are_one_line_and_exit_2(tiny_room, tmp_path, capsys, case, command):
    folder = scenesplat_room(tiny_room, tmp_path / "s", "segment20")
    damage, message = DAMAGE[case]
    damage(folder)
    args = {"train": ["train", str(folder), "--out", str(tmp_path / "run"), "--steps", "1"],
            "eval": ["eval", str(folder), "--features", str(folder / "coord.npy"), "--out", str(tmp_path / "e")]}
    assert main(args[command]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if re.match(r"qr-cl( \w+)?: error: ", line)]   # not progress bars
    assert len(lines) == 1 and "Traceback" not in err, err
    assert re.search(message, lines[0]), lines[0]


def test_training_needs_frames(tiny_room, tmp_path, capsys):
    folder = scenesplat_room(tiny_room, tmp_path / "s", "segment20")
    (folder / "transforms_train.json").unlink()
    assert load_scene_folder(folder).frames == []
    assert main(["train", str(folder), "--out", str(tmp_path / "run"), "--steps", "1"]) == 2
    assert f"{folder}: no frames to train on" in capsys.readouterr().err
