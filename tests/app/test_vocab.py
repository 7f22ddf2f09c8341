"""The real CLIP text table shipped as package data, and ClassTable built from it by name."""
import numpy as np
import pytest

from qr_cl.app.evaluation.metrics import NYU40_NAMES, SUBSETS
from qr_cl.app.vocab import ClassTable, scannet200


def test_the_shipped_table_is_the_real_one(shared_data):
    """The package's copy (what a user's clone has) equals the shared original, with unit rows."""
    names, table = scannet200()
    original = np.load(shared_data / "clip-text-scannet200" / "scannet200_clip_vitb32.npy").astype(np.float32)
    assert len(names) == 200 and table.shape == (200, 512)
    np.testing.assert_allclose(table, original / np.linalg.norm(original, axis=1, keepdims=True), atol=1e-6)


def test_real_clip_classes_are_confusable():
    t = ClassTable.from_names(["chair", "office chair", "table", "desk", "wall", "door"])
    sim = t.similarity()
    assert np.allclose(np.diag(sim), 1, atol=1e-5)
    assert sim[0, 1] > 0.9 and sim[2, 3] > 0.9 and sim[4, 5] > 0.8
    off = sim[~np.eye(len(sim), dtype=bool)]
    assert off.min() > 0.5                       # nothing like random 512-D prototypes (cos ~ 0)


def test_the_19_scannet_classes_are_all_there():
    names = [NYU40_NAMES[i] for i in SUBSETS[19]]
    t = ClassTable.from_names(names)
    assert t.names == tuple(names) and t.embeddings.shape == (19, 512)


def test_unknown_names_are_refused_with_near_matches():
    with pytest.raises(KeyError, match=r"'chiar' \(closest: chair.*'zzz' \(closest: none\)"):
        ClassTable.from_names(["wall", "chiar", "zzz"])
