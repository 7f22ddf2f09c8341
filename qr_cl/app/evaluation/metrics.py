"""Open-vocabulary 3D segmentation metrics (OpenGaussian/ScanNet protocol): mIoU and mAcc.

Class ids are NYU40 ids. :data:`SUBSETS` holds the 19 / 15 / 10 evaluated classes; :data:`NYU40_NAMES`
names them (plus the small objects the synthetic rooms place on furniture: pillow, books,
television, box and lamp, unlisted classes that evaluation ignores).
"""
from __future__ import annotations

import numpy as np

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
    unlisted classes) are ignored; a prediction outside ``class_ids`` raises ValueError.
    """
    pred, gt = np.asarray(pred).ravel(), np.asarray(gt).ravel()
    if pred.shape != gt.shape:
        raise ValueError(f"pred has {pred.size} elements, gt has {gt.size}")
    ids = np.asarray(class_ids, np.int64)
    lut = {int(c): i for i, c in enumerate(ids)}
    gt_idx = np.array([lut.get(int(c), -1) for c in gt], np.int64) if gt.size else np.zeros(0, np.int64)
    keep = gt_idx >= 0
    pred_idx = np.array([lut.get(int(c), -1) for c in pred[keep]], np.int64)
    if (pred_idx < 0).any():
        raise ValueError(f"predictions contain ids outside the evaluated classes {ids.tolist()}")
    k = len(ids)
    return np.bincount(gt_idx[keep] * k + pred_idx, minlength=k * k).reshape(k, k)


def miou_macc(pred: np.ndarray, gt: np.ndarray, class_ids) -> dict:
    """mIoU and mAcc (fractions in [0,1]) over the classes of ``class_ids`` present in ``gt``.

    IoU_c = TP / (TP + FP + FN), Acc_c = TP / (TP + FN) (per-class recall), both counted on the
    elements whose ground truth is one of ``class_ids``. Returns {"miou", "macc", "per_class":
    {id: {"iou", "acc", "support"}}, "n_evaluated"}; miou/macc are NaN when no class is present.
    """
    ids = list(class_ids)
    cm = confusion_matrix(pred, gt, ids).astype(np.float64)
    tp = np.diag(cm)
    support = cm.sum(1)
    predicted = cm.sum(0)
    present = support > 0
    iou = tp / np.maximum(support + predicted - tp, 1)
    acc = tp / np.maximum(support, 1)
    per_class = {int(c): {"iou": float(iou[i]), "acc": float(acc[i]), "support": int(support[i])}
                 for i, c in enumerate(ids) if present[i]}
    return {"miou": float(iou[present].mean()) if present.any() else float("nan"),
            "macc": float(acc[present].mean()) if present.any() else float("nan"),
            "per_class": per_class, "n_evaluated": int(support.sum())}
