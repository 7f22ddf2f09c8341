"""Label spaces: ScanNet20 / ScanNet200 / NYU40 ids onto the evaluation's NYU40 ids."""
from __future__ import annotations

import numpy as np
import pytest

from qr_cl.app.evaluation.metrics import SUBSETS
from qr_cl.app.scenes.label_spaces import SCANNET20_NYU40, SCANNET200_NYU40, SEGMENT_SPACES, SPACES, to_nyu40
from qr_cl.app.vocab import scannet200
from qr_cl.scene.scenesplat import IGNORE_LABEL


@pytest.mark.parametrize("space", sorted(SPACES))
def test_ignore_index_stays_and_every_id_maps(space):
    ids = np.array(sorted(SPACES[space]) + [IGNORE_LABEL] * 3, np.int16)   # SceneSplat saves int16
    out = to_nyu40(ids, space)
    assert out.dtype == np.int64 and out.shape == ids.shape
    assert out[-3:].tolist() == [IGNORE_LABEL] * 3
    assert set(out[:-3].tolist()) <= set(range(1, 41))


def test_scannet20_is_the_20_benchmark_classes_in_order():
    assert to_nyu40(np.arange(20), "scannet20").tolist() == [
        1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39]


def test_nyu40_is_the_identity():
    assert to_nyu40(np.arange(1, 41), "nyu40").tolist() == list(range(1, 41))


@pytest.mark.parametrize("space", ["scannet20", "scannet200"])
def test_every_evaluated_class_is_reachable(space):
    reached = set(to_nyu40(np.array(sorted(SPACES[space])), space).tolist())
    assert set(SUBSETS[19]) <= reached


@pytest.mark.parametrize("index, name, nyu40", [
    (0, "wall", 1), (1, "chair", 5), (2, "floor", 2), (3, "table", 7), (5, "couch", 6),
    (25, "kitchen cabinet", 3), (9, "office chair", 5), (47, "shower curtain", 28), (15, "toilet", 33),
    (36, "bathtub", 36), (199, "mattress", 4), (120, "mini fridge", 24), (196, "poster", 11),
    (118, "doorframe", 8), (7, "shelf", 15), (11, "pillow", 18), (28, "tv", 25), (17, "monitor", 40),
    (48, "trash can", 39), (50, "stairs", 38), (172, "object", 40), (109, "mat", 20),
])
def test_known_scannet200_classes(index, name, nyu40):
    assert SCANNET200_NYU40[index][0] == name
    assert to_nyu40(np.array([index]), "scannet200").tolist() == [nyu40]


def test_scannet200_classes_on_the_19_evaluated():
    on_19 = {}
    for name, nyu40 in SCANNET200_NYU40:
        if nyu40 in SUBSETS[19]:
            on_19.setdefault(nyu40, set()).add(name)
    assert on_19 == {
        1: {"wall", "shower wall", "closet wall"}, 2: {"floor", "shower floor"},
        3: {"cabinet", "kitchen cabinet", "file cabinet", "bathroom vanity", "bathroom cabinet"},
        4: {"bed", "mattress"}, 5: {"chair", "office chair", "armchair", "sofa chair", "folded chair"},
        6: {"couch"}, 7: {"table", "coffee table", "end table", "dining table"},
        8: {"door", "doorframe", "shower door", "closet door", "bathroom stall door"},
        9: {"window"}, 10: {"bookshelf"}, 11: {"picture", "poster"},
        12: {"counter", "kitchen counter", "bathroom counter"}, 14: {"desk"}, 16: {"curtain"},
        24: {"refrigerator", "mini fridge"}, 28: {"shower curtain"}, 33: {"toilet"}, 34: {"sink"},
        36: {"bathtub"},
    }


def test_scannet200_order_matches_the_shipped_class_names():
    # vocab/names.json is the ScanNet200 class list of another source (OVIR-3D), same order
    assert [name for name, _ in SCANNET200_NYU40] == list(scannet200()[0])


@pytest.mark.parametrize("space, bad", [
    ("scannet20", 20), ("scannet20", -2), ("scannet200", 200), ("nyu40", 0), ("nyu40", 41)])
def test_ids_outside_the_space_raise_naming_it(space, bad):
    with pytest.raises(ValueError, match=rf"^{space} labels: 2 ids outside .*first {bad}$"):
        to_nyu40(np.array([IGNORE_LABEL, 1, bad, bad]), space)


def test_bad_input_raises():
    with pytest.raises(ValueError, match="unknown label space 'scannet'"):
        to_nyu40(np.zeros(3, np.int64), "scannet")
    with pytest.raises(ValueError, match="integers"):
        to_nyu40(np.zeros(3, np.float32), "scannet20")
    with pytest.raises(ValueError, match=r"\[N\] or \[N,1\]"):
        to_nyu40(np.zeros((3, 2), np.int64), "scannet20")


def test_column_labels_are_flattened():
    column = np.array([[0], [IGNORE_LABEL], [19]], np.int16)
    assert to_nyu40(column, "scannet20").tolist() == [1, IGNORE_LABEL, 39]


def test_segment_spaces_name_spaces():
    assert SEGMENT_SPACES == {"segment20": "scannet20", "segment200": "scannet200"}
    assert set(SEGMENT_SPACES.values()) <= set(SPACES)
    assert len(SCANNET20_NYU40) == 20 and len(SCANNET200_NYU40) == 200
