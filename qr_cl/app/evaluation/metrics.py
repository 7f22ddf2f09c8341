"""Open-vocabulary 3D segmentation metrics (OpenGaussian/ScanNet protocol): mIoU and mAcc.

Class ids are NYU40 ids. :data:`SUBSETS` holds the 19 / 15 / 10 evaluated classes; :data:`NYU40_NAMES`
names them (plus the small objects the synthetic rooms place on furniture: pillow, books,
television, box and lamp, unlisted classes that evaluation ignores). A prediction of
:data:`UNLABELLED` (a Gaussian without a feature, e.g. one no pixel registers) names no class: it
counts against its ground-truth class's IoU and accuracy and for no other class.
"""
from __future__ import annotations

import numpy as np

#: The prediction of a Gaussian that has no feature to classify.
UNLABELLED = -1

NYU40_NAMES: dict[int, str] = {
    1: "wall", 2: "floor", 3: "cabinet", 4: "bed", 5: "chair", 6: "sofa", 7: "table", 8: "door",
    9: "window", 10: "bookshelf", 11: "picture", 12: "counter", 14: "desk", 16: "curtain",
    18: "pillow", 23: "books", 24: "refrigerator", 25: "television", 28: "shower curtain", 29: "box",
    33: "toilet", 34: "sink", 35: "lamp", 36: "bathtub",
}

SUBSETS: dict[int, tuple[int, ...]] = {
    19: (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36),
    15: (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 14, 16, 33, 34),
    10: (1, 2, 4, 5, 6, 7, 8, 9, 10, 33),
}


def confusion_matrix(pred: np.ndarray, gt: np.ndarray, class_ids) -> np.ndarray:
    """Confusion counts [K,K] (row = ground truth, column = prediction) over ``class_ids`` (K ids).

    pred, gt: [N] integer class ids. Elements whose ground truth is not in ``class_ids`` (e.g. -1,
    unlisted classes) are ignored; predictions of :data:`UNLABELLED` are in no column; any other
    prediction outside ``class_ids`` raises ValueError.
    """
    pred, gt = np.asarray(pred).ravel(), np.asarray(gt).ravel()
    if pred.shape != gt.shape:
        raise ValueError(f"pred has {pred.size} elements, gt has {gt.size}")
    ids = np.asarray(class_ids, np.int64)
    lut = {int(c): i for i, c in enumerate(ids)}
    gt_idx = np.array([lut.get(int(c), -1) for c in gt], np.int64) if gt.size else np.zeros(0, np.int64)
    keep = gt_idx >= 0
    pred_idx = np.array([lut.get(int(c), -1) for c in pred[keep]], np.int64)
    if ((pred_idx < 0) & (pred[keep] != UNLABELLED)).any():
        raise ValueError(f"predictions contain ids outside the evaluated classes {ids.tolist()}")
    k = len(ids)
    named = pred_idx >= 0
    return np.bincount(gt_idx[keep][named] * k + pred_idx[named], minlength=k * k).reshape(k, k)


def miou_macc(pred: np.ndarray, gt: np.ndarray, class_ids) -> dict:
    """mIoU and mAcc (fractions in [0,1]) over the classes of ``class_ids`` present in ``gt``.

    IoU_c = TP / (TP + FP + FN), Acc_c = TP / (TP + FN) (per-class recall), both counted on the
    elements whose ground truth is one of ``class_ids`` (:data:`UNLABELLED` predictions among them
    are misses). Returns {"miou", "macc", "per_class": {id: {"iou", "acc", "support"}},
    "n_evaluated", "unlabelled"}; miou/macc are NaN when no class is present.
    """
    ids = list(class_ids)
    cm = confusion_matrix(pred, gt, ids).astype(np.float64)
    tp = np.diag(cm)
    evaluated = np.isin(np.asarray(gt).ravel(), np.asarray(ids, np.int64))
    support = np.array([np.count_nonzero(np.asarray(gt).ravel() == c) for c in ids], np.float64)
    predicted = cm.sum(0)
    present = support > 0
    iou = tp / np.maximum(support + predicted - tp, 1)
    acc = tp / np.maximum(support, 1)
    per_class = {int(c): {"iou": float(iou[i]), "acc": float(acc[i]), "support": int(support[i])}
                 for i, c in enumerate(ids) if present[i]}
    return {"miou": float(iou[present].mean()) if present.any() else float("nan"),
            "macc": float(acc[present].mean()) if present.any() else float("nan"),
            "per_class": per_class, "n_evaluated": int(support.sum()),
            "unlabelled": int(np.count_nonzero(evaluated & (np.asarray(pred).ravel() == UNLABELLED)))}
