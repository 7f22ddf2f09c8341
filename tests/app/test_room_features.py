"""The simulated CLIP features of the synthetic rooms: real CLIP anchors, the calibrated mask
noise, the orthogonal-prototype model kept for comparison, and the cache keys they make."""
from __future__ import annotations

import json

import numpy as np
import pytest

from qr_cl.app.evaluation.metrics import NYU40_NAMES, SUBSETS
from qr_cl.app.scenes.room_config import SyntheticConfig
from qr_cl.app.scenes.room_features import (RoomFeatures, clip_anchors, expected_mask_accuracy, mask_accuracy,
                                            orthogonal_prototypes)
from qr_cl.app.scenes.synthetic import room_folder
from qr_cl.app.vocab import ClassTable


def test_clip_anchors_are_the_shipped_text_embeddings():
    anchors = clip_anchors(512, 0)
    table = ClassTable.from_names(["table", "desk", "sofa", "books", "television"])
    for c, row in zip((7, 14, 6, 23, 25), table.embeddings):
        assert np.allclose(anchors[c], row, atol=1e-6)
    assert set(anchors) == set(NYU40_NAMES)
    assert anchors[7] @ anchors[14] > 0.9                 # table and desk: real CLIP confuses them
    low = clip_anchors(32, 0)
    assert all(v.shape == (32,) and abs(np.linalg.norm(v) - 1) < 1e-9 for v in low.values())
    with pytest.raises(ValueError, match="512"):
        clip_anchors(600, 0)


def test_default_mask_noise_gives_clip_like_accuracy():
    """One mask's feature names its own class among the 19 about as often as CLIP on object
    crops (60-75 %), and its cosine to its own text feature is CLIP-like (0.2-0.35)."""
    cfg = SyntheticConfig()
    assert 0.6 <= expected_mask_accuracy(cfg) <= 0.75
    model = RoomFeatures(cfg)
    classes = np.repeat(np.asarray(SUBSETS[19]), 50)
    feats = model.masks(classes, np.random.default_rng(1))
    own = np.einsum("md,md->m", feats, np.stack([model.text()[int(c)] for c in classes]))
    assert 0.2 < own.mean() < 0.35
    assert expected_mask_accuracy(SyntheticConfig(clip_noise=1.0)) > 0.95      # the noise is what calibrates
    assert expected_mask_accuracy(SyntheticConfig(clip_noise=6.0)) < 0.5


def test_mask_accuracy_counts_evaluated_classes_only():
    text = orthogonal_prototypes(16, 0)
    feats = np.stack([text[7], text[14], text[35], text[7]])
    assert mask_accuracy(feats, np.array([7, 7, 35, 7]), text) == pytest.approx(2 / 3)     # lamp not evaluated
    assert np.isnan(mask_accuracy(feats[2:3], np.array([35]), text))


def test_orthogonal_model_and_cache_keys():
    clip, ortho = SyntheticConfig(), SyntheticConfig(features="orthogonal")
    assert clip.key() != ortho.key()
    assert "mask_noise" not in clip.params() and "clip_noise" in clip.params()
    assert "clip_noise" not in ortho.params() and "mask_noise" in ortho.params()
    text = RoomFeatures(ortho).text()
    off = [text[a] @ text[b] for a in SUBSETS[19] for b in SUBSETS[19] if a < b]
    assert max(abs(v) for v in off) < 0.35                # nearly orthogonal classes
    with pytest.raises(ValueError, match="features="):
        SyntheticConfig(features="siglip")


def test_a_room_records_its_measured_mask_accuracy(tmp_path):
    cfg = SyntheticConfig(seed=5, n_gaussians=4000, n_objects=4, n_wall_objects=2, n_views=6, width=80, height=60)
    folder = room_folder(cfg, tmp_path)
    meta = json.loads((folder / "synthetic.json").read_text())
    classes = json.loads((folder / "classes.json").read_text())["classes"]
    desk = next(c for c in classes if c["name"] == "desk")
    assert np.allclose(desk["text_feature"], clip_anchors(512, 0)[14], atol=1e-6)
    assert 0.4 < meta["mask_accuracy19"] < 0.95           # a few hundred masks around the calibrated 70 %


def test_the_image_text_offset_favours_no_class():
    model = RoomFeatures(SyntheticConfig())
    assert np.linalg.norm(model.offset) == pytest.approx(0.5)
    assert max(abs(model.offset @ a) for a in model.anchors.values()) < 1e-9
    tiny = RoomFeatures(SyntheticConfig(dim=16))         # fewer channels than classes: offset as drawn
    assert np.isfinite(tiny.offset).all() and np.linalg.norm(tiny.offset) == pytest.approx(0.5)
