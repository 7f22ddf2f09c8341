"""``qr-cl features`` end to end with tiny random-weight models: LangSplat's files from rendered
fox views that ``qr-cl train`` trains on, byte-identical resume, and a one-line error for each
bad input."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from qr_cl.app import cli
from qr_cl.app.features import command, store
from qr_cl.app.scenes.folders import level_rows, load_scene_folder
from qr_cl.scene import load_ply, orbit_cameras
from tests.app.features_helpers import CLASS_WORDS, drawn_scene, run_features, write_cameras, write_models


@pytest.fixture(scope="module")
def models(tmp_path_factory):
    return write_models(tmp_path_factory.mktemp("weights"))


@pytest.mark.data
def test_rendered_fox_views_train(shared_data, models, tmp_path):
    fox = shared_data / "wakufactory-fox" / "fox.ply"
    scene = tmp_path / "fox"
    scene.mkdir()
    (scene / "point_cloud.ply").symlink_to(fox)
    cams = orbit_cameras(load_ply(fox).means, 3, 64, 48, up_axis=1)
    for i, cam in enumerate(cams):
        cam.name = f"{i:03d}_rgb"
    write_cameras(scene / "cameras.json", cams)
    assert cli.main(["render", str(fox), "--cameras", str(scene / "cameras.json"), "--out", str(tmp_path / "views")]) == 0
    assert run_features(scene, tmp_path / "views", models, "--points-per-side", "4", "--classes", ",".join(CLASS_WORDS)) == 0

    counts = []
    for cam in cams:
        s = np.load(scene / "language_features" / f"{cam.name}_s.npy")
        f = np.load(scene / "language_features" / f"{cam.name}_f.npy")
        assert s.dtype == np.float32 and s.shape == (4, 48, 64)          # LangSplat's dtypes and layout
        assert f.dtype == np.float32 and f.ndim == 2 and f.shape[1] == 32
        assert np.all(s == np.round(s)) and s.min() >= -1 and s.max() < len(f)
        assert (s == -1).any() and (s >= 0).any()
        np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1, atol=1e-5)
        present = [np.unique(level[level >= 0]).astype(int) for level in s]
        for j, ids in enumerate(present):          # level j's ids: one block after the levels before it
            later = [p.min() for p in present[j + 1:] if len(p)]
            if len(ids):
                assert ids.max() < (later[0] if later else len(f))
                assert all(ids.min() > p.max() for p in present[:j] if len(p))
                assert level_rows(s.astype(np.int64), j, len(f))[0] == ids.min()
        counts.append([len(p) for p in present])
    data = load_scene_folder(scene)
    assert len(data.frames) == 3 and data.feature_dim == 32
    assert data.classes.names == CLASS_WORDS and data.classes.text_features.shape == (5, 32)
    record = json.loads((scene / "classes.json").read_text())["encoder"]
    assert record["model"].startswith("ViT-") and len(record["sha256"]) == 64

    out = tmp_path / "run"
    level = int(np.argmax(np.sum(counts, 0)))                  # random SAM weights: some levels have one mask
    assert max(c[level] for c in counts) >= 2
    assert cli.main(["train", str(scene), "--level", str(level), "--out", str(out), "--steps", "3", "--views", "1", "--rays", "64",
                     "--net", "tiny", "--grid-size", "0.05", "--checkpoint-every", "3"]) == 0
    log = json.loads((out / "train_log.json").read_text())
    assert (out / "checkpoint.pt").is_file() and len(log["steps"] if "steps" in log else log) >= 1


def _tree(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_resume_writes_the_same_bytes(models, tmp_path, monkeypatch):
    straight, images = drawn_scene(tmp_path / "a")
    assert run_features(straight, images, models) == 0

    resumed, images_b = drawn_scene(tmp_path / "b")
    written = []
    real_write = store.write_frame

    def write_then_stop(folder, stem, ids, features):
        if written:
            raise KeyboardInterrupt
        real_write(folder, stem, ids, features)
        written.append(stem)
    monkeypatch.setattr(store, "write_frame", write_then_stop)
    with pytest.raises(KeyboardInterrupt):
        run_features(resumed, images_b, models)
    monkeypatch.undo()
    lang = resumed / "language_features"
    assert sorted(p.name for p in lang.glob("*.npy")) == ["view_0_f.npy", "view_0_s.npy"]
    (lang / ".view_1_f.npy.x.tmp").write_bytes(b"half a file")            # a kill's leftover
    (lang / "view_2_f.npy").write_bytes(b"no _s.npy yet: not done")       # half a frame is redone
    assert run_features(resumed, images_b, models) == 0
    assert not (lang / ".view_1_f.npy.x.tmp").exists()                    # removed as stale
    assert _tree(lang) == _tree(straight / "language_features")


def _fails(capsys, code, *words):
    err = capsys.readouterr().err.strip().splitlines()[-1].split("\r")[-1]   # after earlier runs' progress bars
    assert code == 2 and err.startswith("qr-cl: error: "), err
    for word in words:
        assert str(word) in err, (word, err)
    return err


def test_bad_weights_files(models, tmp_path, capsys):
    scene, images = drawn_scene(tmp_path / "s", frames=1)
    missing = tmp_path / "nowhere.bin"
    _fails(capsys, run_features(scene, images, {**models, "clip": missing}), missing, "--clip-weights")
    corrupt = tmp_path / "sam_vit_h_4b8939.pth"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip" * 10)
    _fails(capsys, run_features(scene, images, {**models, "sam": corrupt}), corrupt, "not a readable weights file")
    cut = tmp_path / "cut.safetensors"
    cut.write_bytes(models["clip"].read_bytes()[:-1000])
    _fails(capsys, run_features(scene, images, {**models, "clip": cut}), cut, "truncated")
    empty = tmp_path / "empty.pth"
    empty.write_bytes(b"")
    _fails(capsys, run_features(scene, images, {**models, "sam": empty}), empty, "empty")
    _fails(capsys, run_features(scene, images, {"clip": models["sam"], "sam": models["sam"]}),
           models["sam"], "a SAM checkpoint")
    _fails(capsys, run_features(scene, images, {"clip": models["clip"], "sam": models["clip"]}),
           models["clip"], "a CLIP checkpoint")


def test_mismatched_encoder(models, tmp_path, capsys):
    scene, images = drawn_scene(tmp_path / "s", frames=1)
    _fails(capsys, run_features(scene, images, models, "--clip-model", "ViT-L-14"), models["clip"], "ViT-L-14")
    _fails(capsys, run_features(scene, images, models, "--clip-model", "resnet50"), "resnet50")
    assert run_features(scene, images, models) == 0
    other = write_models(tmp_path / "other")
    sam_bytes = other["sam"].read_bytes()
    (tmp_path / "other" / "sam_vit_tiny.pth").write_bytes(sam_bytes)
    import torch
    state = torch.load(other["sam"], weights_only=True)
    state["mask_decoder.iou_token.weight"] += 1
    torch.save(state, other["sam"])
    _fails(capsys, run_features(scene, images, {**models, "sam": other["sam"]}), store.RECORD, "sam", "--overwrite")
    assert run_features(scene, images, {**models, "sam": other["sam"]}, "--overwrite") == 0
    (scene / "classes.json").write_text(json.dumps({"classes": []}))
    _fails(capsys, run_features(scene, images, models, "--overwrite", "--classes", "wall"), "classes.json",
           "not written by qr-cl features")


def test_bad_images(models, tmp_path, capsys):
    scene, images = drawn_scene(tmp_path / "s", frames=2)
    moved = images / "view_1.png"
    shutil.move(moved, tmp_path / "away.png")
    _fails(capsys, run_features(scene, images, models), "view_1", "no image for camera")
    (images / "view_1.jpg").write_bytes(b"not a jpeg")
    _fails(capsys, run_features(scene, images, models), images / "view_1.jpg", "not a readable image")
    (images / "view_1.jpg").unlink()
    from PIL import Image
    Image.new("RGB", (48, 48)).save(images / "view_1.JPG")
    _fails(capsys, run_features(scene, images, models), images / "view_1.JPG", "48x48", "aspect")
    Image.new("RGB", (32, 24)).save(images / "view_1.JPG")          # half the size, same aspect: fine
    assert run_features(scene, images, models) == 0
    assert np.load(scene / "language_features" / "view_1_s.npy").shape == (4, 24, 32)


def test_bad_options(models, tmp_path, capsys):
    scene, images = drawn_scene(tmp_path / "s", frames=1)
    _fails(capsys, run_features(scene, images, models, "--device", "nodevice"), "--device nodevice")
    _fails(capsys, run_features(scene, tmp_path / "nope", models), tmp_path / "nope", "--images")
    _fails(capsys, run_features(scene, images, models, "--classes", " , "), "no class names")
    (tmp_path / "w").mkdir()
    bare = write_models(tmp_path / "w")
    (tmp_path / "w" / "bpe_simple_vocab_16e6.txt.gz").unlink()
    _fails(capsys, run_features(scene, images, bare, "--classes", "wall"), "bpe_simple_vocab_16e6.txt.gz", "--clip-vocab")


def test_extra_modules_are_named(monkeypatch, capsys):
    monkeypatch.setattr(command, "EXTRA_MODULES", ("scipy", "no_such_module_qrcl"))
    _fails(capsys, cli.main(["features", "x", "--images", "y", "--clip-weights", "a", "--sam-weights", "b"]),
           "no_such_module_qrcl", ".[features]")


def test_transforms_frames_name_the_photos(models, tmp_path):
    """A SceneSplat-style folder has transforms_train.json, no cameras.json: each frame's
    ``file_path`` names its photo (another extension is fine) and its feature files."""
    scene, images = drawn_scene(tmp_path, frames=2)
    (scene / "cameras.json").unlink()
    frames = [{"file_path": f"images/view_{i}.jpg", "transform_matrix": np.diag([1.0, -1, -1, 1]).tolist()}
              for i in range(2)]
    (scene / "transforms_train.json").write_text(json.dumps({"fl_x": 50.0, "w": 64, "h": 48, "frames": frames}))
    assert run_features(scene, images, models) == 0
    assert sorted(p.name for p in (scene / "language_features").glob("*.npy")) == [
        "view_0_f.npy", "view_0_s.npy", "view_1_f.npy", "view_1_s.npy"]
