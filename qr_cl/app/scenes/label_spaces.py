"""Id spaces of published ScanNet labels and their NYU40 ids, the ids the evaluation scores on.

SceneSplat-7K's ScanNet folders (Pointcept-style folders of .npy files) label each Gaussian in
ScanNet's benchmark id spaces, not in NYU40; :func:`to_nyu40` maps them onto the NYU40 ids of
:mod:`qr_cl.app.evaluation.metrics` (``labels/gaussian_labels.npy``). Spaces (:data:`SPACES`):

- ``"scannet20"`` (``segment20.npy``): train ids 0..19 of the ScanNet20 benchmark classes,
  :data:`SCANNET20_NYU40`;
- ``"scannet200"`` (``segment200.npy``): train ids 0..199 of the ScanNet200 benchmark classes,
  :data:`SCANNET200_NYU40`;
- ``"nyu40"``: NYU40 ids 1..40, unchanged.

In every space :data:`IGNORE_LABEL` (-1) is "no label" and stays -1. See docs/label-spaces.md.
"""
from __future__ import annotations

import numpy as np

from ...scene import IGNORE_LABEL


#: ScanNet20 train id (index) -> NYU40 id: the NYU40 ids of ScanNet's 20 benchmark classes
#: (wall, floor, cabinet, bed, chair, sofa, table, door, window, bookshelf, picture, counter, desk,
#: curtain, refrigerator, shower curtain, toilet, sink, bathtub, otherfurniture), in the order of
#: ``VALID_CLASS_IDS_20`` of Pointcept's ``scannet200_constants.py``, by which its ScanNet
#: preprocessing (and SceneSplat's) turns a point's NYU40 id into its ``segment20`` id.
SCANNET20_NYU40: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39)

#: ScanNet200 train id (index) -> (class name, NYU40 id). The classes are ScanNet200's
#: ``CLASS_LABELS_200`` in the order of its ``VALID_CLASS_IDS_200`` (raw ScanNet category ids;
#: Pointcept's ``scannet200_constants.py``); a class's NYU40 id is the ``nyu40id`` of the row of
#: ScanNet's ``scannetv2-labels.combined.tsv`` whose ``raw_category`` is the class's name (ids
#: written out here, not read from that file). Two classes have a rarer spelling with another
#: NYU40 id in the tsv ("pipes" 38 for pipe 40, "shower doors" 38 for shower door 8), so on those
#: Gaussians this table and ``segment20`` disagree (``segment20`` leaves shower doors unlabelled).
#: Classes whose NYU40 class is otherstructure (38), otherfurniture (39) or otherprop (40) keep
#: those ids; the evaluation ignores them like every class outside its subsets.
#: The 42 classes that land on the 19 evaluated classes (``metrics.SUBSETS[19]``): wall 1 (wall,
#: shower wall, closet wall), floor 2 (floor, shower floor), cabinet 3 (cabinet, kitchen cabinet,
#: file cabinet, bathroom vanity, bathroom cabinet), bed 4 (bed, mattress), chair 5 (chair, office
#: chair, armchair, sofa chair, folded chair), sofa 6 (couch), table 7 (table, coffee table, end
#: table, dining table), door 8 (door, doorframe, shower door, closet door, bathroom stall door),
#: window 9, bookshelf 10, picture 11 (picture, poster), counter 12 (counter, kitchen counter,
#: bathroom counter), desk 14, curtain 16, refrigerator 24 (refrigerator, mini fridge), shower
#: curtain 28, toilet 33, sink 34, bathtub 36.
SCANNET200_NYU40: tuple[tuple[str, int], ...] = (
    ("wall", 1), ("chair", 5), ("floor", 2), ("table", 7), ("door", 8), ("couch", 6),                 # 0-5
    ("cabinet", 3), ("shelf", 15), ("desk", 14), ("office chair", 5), ("bed", 4), ("pillow", 18),     # 6-11
    ("sink", 34), ("picture", 11), ("window", 9), ("toilet", 33), ("bookshelf", 10),                  # 12-16
    ("monitor", 40), ("curtain", 16), ("book", 23), ("armchair", 5), ("coffee table", 7),             # 17-21
    ("box", 29), ("refrigerator", 24), ("lamp", 35), ("kitchen cabinet", 3), ("towel", 27),           # 22-26
    ("clothes", 21), ("tv", 25), ("nightstand", 32), ("counter", 12), ("dresser", 17),                # 27-31
    ("stool", 40), ("cushion", 18), ("plant", 40), ("ceiling", 22), ("bathtub", 36),                  # 32-36
    ("end table", 7), ("dining table", 7), ("keyboard", 40), ("bag", 37), ("backpack", 40),           # 37-41
    ("toilet paper", 40), ("printer", 40), ("tv stand", 39), ("whiteboard", 30), ("blanket", 40),     # 42-46
    ("shower curtain", 28), ("trash can", 39), ("closet", 39), ("stairs", 38), ("microwave", 40),     # 47-51
    ("stove", 38), ("shoe", 40), ("computer tower", 40), ("bottle", 40), ("bin", 40),                 # 52-56
    ("ottoman", 39), ("bench", 39), ("board", 38), ("washing machine", 39), ("mirror", 19),           # 57-61
    ("copier", 40), ("basket", 40), ("sofa chair", 5), ("file cabinet", 3), ("fan", 40),              # 62-66
    ("laptop", 40), ("shower", 38), ("paper", 26), ("person", 31), ("paper towel dispenser", 40),     # 67-71
    ("oven", 38), ("blinds", 13), ("rack", 39), ("plate", 40), ("blackboard", 38), ("piano", 39),     # 72-77
    ("suitcase", 40), ("rail", 38), ("radiator", 39), ("recycling bin", 39), ("container", 40),       # 78-82
    ("wardrobe", 39), ("soap dispenser", 40), ("telephone", 40), ("bucket", 40), ("clock", 40),       # 83-87
    ("stand", 39), ("light", 38), ("laundry basket", 40), ("pipe", 40), ("clothes dryer", 39),        # 88-92
    ("guitar", 40), ("toilet paper holder", 40), ("seat", 39), ("speaker", 40), ("column", 38),       # 93-97
    ("bicycle", 40), ("ladder", 39), ("bathroom stall", 38), ("shower wall", 1), ("cup", 40),         # 98-102
    ("jacket", 40), ("storage bin", 40), ("coffee maker", 40), ("dishwasher", 38),                    # 103-106
    ("paper towel roll", 40), ("machine", 40), ("mat", 20), ("windowsill", 38), ("bar", 38),          # 107-111
    ("toaster", 40), ("bulletin board", 38), ("ironing board", 39), ("fireplace", 38),                # 112-115
    ("soap dish", 40), ("kitchen counter", 12), ("doorframe", 8), ("toilet paper dispenser", 40),     # 116-119
    ("mini fridge", 24), ("fire extinguisher", 40), ("ball", 40), ("hat", 40),                        # 120-123
    ("shower curtain rod", 40), ("water cooler", 39), ("paper cutter", 40), ("tray", 40),             # 124-127
    ("shower door", 8), ("pillar", 38), ("ledge", 38), ("toaster oven", 40), ("mouse", 40),           # 128-132
    ("toilet seat cover dispenser", 40), ("furniture", 39), ("cart", 40), ("storage container", 40),  # 133-136
    ("scale", 40), ("tissue box", 40), ("light switch", 38), ("crate", 39), ("power outlet", 40),     # 137-141
    ("decoration", 40), ("sign", 40), ("projector", 40), ("closet door", 8), ("vacuum cleaner", 40),  # 142-146
    ("candle", 40), ("plunger", 40), ("stuffed animal", 40), ("headphones", 40), ("dish rack", 40),   # 147-151
    ("broom", 40), ("guitar case", 40), ("range hood", 38), ("dustpan", 40), ("hair dryer", 40),      # 152-156
    ("water bottle", 40), ("handicap bar", 38), ("purse", 40), ("vent", 40), ("shower floor", 2),     # 157-161
    ("water pitcher", 40), ("mailbox", 29), ("bowl", 40), ("paper bag", 37), ("alarm clock", 40),     # 162-166
    ("music stand", 39), ("projector screen", 38), ("divider", 40), ("laundry detergent", 40),        # 167-170
    ("bathroom counter", 12), ("object", 40), ("bathroom vanity", 3), ("closet wall", 1),             # 171-174
    ("laundry hamper", 40), ("bathroom stall door", 8), ("ceiling light", 38), ("trash bin", 39),     # 175-178
    ("dumbbell", 40), ("stair rail", 38), ("tube", 40), ("bathroom cabinet", 3), ("cd case", 40),     # 179-183
    ("closet rod", 40), ("coffee kettle", 40), ("structure", 38), ("shower head", 38),                # 184-187
    ("keyboard piano", 39), ("case of water bottles", 40), ("coat rack", 40),                         # 188-190
    ("storage organizer", 40), ("folded chair", 5), ("fire alarm", 40), ("power strip", 40),          # 191-194
    ("calendar", 40), ("poster", 11), ("potted plant", 40), ("luggage", 40), ("mattress", 4),         # 195-199
)

#: Every space -> {id in the space: its NYU40 id}; :data:`IGNORE_LABEL` is in none of them.
SPACES: dict[str, dict[int, int]] = {
    "scannet20": dict(enumerate(SCANNET20_NYU40)),
    "scannet200": {i: nyu40 for i, (_, nyu40) in enumerate(SCANNET200_NYU40)},
    "nyu40": {c: c for c in range(1, 41)},
}

#: SceneSplat folder label file (stem of ``<stem>.npy``) -> the space of its ids, in the order a
#: folder's files are preferred. A generic ``segment.npy`` (other datasets) is not here: its space
#: depends on the dataset, so the caller names it.
SEGMENT_SPACES: dict[str, str] = {"segment20": "scannet20", "segment200": "scannet200"}


def to_nyu40(labels: np.ndarray, space: str) -> np.ndarray:
    """NYU40 ids [N] int64 of ``labels`` [N] or [N,1] (integer ids of ``space``, a key of
    :data:`SPACES`; SceneSplat's label files come in either shape).

    :data:`IGNORE_LABEL` stays :data:`IGNORE_LABEL`. ValueError for an unknown space, non-integer
    labels, another shape, or any other id outside the space (naming the space and the first bad ids).
    """
    if space not in SPACES:
        raise ValueError(f"unknown label space {space!r}: choose one of {', '.join(SPACES)}")
    ids = np.asarray(labels)
    if ids.ndim == 0 or ids.shape[1:] not in ((), (1,)) or not np.issubdtype(ids.dtype, np.integer):
        raise ValueError(f"{space} labels must be [N] or [N,1] integers, got {ids.dtype} {list(ids.shape)}")
    ids = ids.reshape(-1).astype(np.int64)
    table = SPACES[space]
    lut = np.zeros(max(table) + 1, np.int64)                       # 0: no id of the space here
    lut[list(table)] = list(table.values())
    inside = (ids >= 0) & (ids < lut.size)
    nyu40 = np.where(inside, lut[np.where(inside, ids, 0)], 0)
    bad = (nyu40 == 0) & (ids != IGNORE_LABEL)
    if bad.any():
        values, first = np.unique(ids[bad], return_index=True)
        shown = ", ".join(map(str, values[np.argsort(first)][:5].tolist()))
        raise ValueError(f"{space} labels: {int(bad.sum())} ids outside the space "
                         f"({min(table)}..{max(table)}, {IGNORE_LABEL} = ignore), first {shown}")
    return np.where(ids == IGNORE_LABEL, IGNORE_LABEL, nyu40)
