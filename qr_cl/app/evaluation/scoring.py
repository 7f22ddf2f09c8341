"""Predictions and their scores: the class of each Gaussian (the text feature most cosine-similar to
its feature), mIoU/mAcc per class subset, and their markdown table."""
from __future__ import annotations

import math

import numpy as np

from ..scenes.folders import ClassTable, SceneData
from .metrics import SUBSETS, UNLABELLED, miou_macc


def predict(features: np.ndarray, classes: ClassTable) -> np.ndarray:
    """Class id [N] of the text feature most cosine-similar to each row of ``features`` [N,C];
    :data:`~.metrics.UNLABELLED` for a zero row (a Gaussian without a feature)."""
    norms = np.linalg.norm(features, axis=1, keepdims=True)
    f = features / np.maximum(norms, 1e-12)
    return np.where(norms[:, 0] > 0, classes.ids[(f @ classes.text_features.T).argmax(1)], UNLABELLED)


def evaluate_features(scene: SceneData, features: np.ndarray, gt: np.ndarray, subsets=(19, 15, 10)) -> dict:
    """mIoU/mAcc of per-Gaussian ``features`` [N,C] against ``gt`` [N] for each class subset:
    {subset: {"miou", "macc", "per_class", "n_evaluated", "classes_present"}}."""
    if scene.classes is None:
        raise ValueError(f"{scene.root}: classes.json is needed for open-vocabulary evaluation")
    if features.shape != (len(scene.gaussians), scene.classes.text_features.shape[1]):
        raise ValueError(f"features have shape {features.shape}, expected "
                         f"({len(scene.gaussians)}, {scene.classes.text_features.shape[1]})")
    results = {}
    for size in subsets:
        table = scene.classes.subset(SUBSETS[size])
        res = miou_macc(predict(features, table), gt, table.ids)
        res["classes_present"] = len(res["per_class"])
        results[int(size)] = res
    return results


def markdown_table(rows: list[dict], subsets=(19, 15, 10)) -> str:
    """A markdown table of ``rows`` ({"method", "scene", "split", subset: {"miou", "macc"}}), values in %."""
    head = "| method | scene | split | " + " | ".join(f"mIoU{s} | mAcc{s}" for s in subsets) + " |\n"
    head += "| --- | --- | --- | " + " | ".join("---: | ---:" for _ in subsets) + " |\n"
    body = ""
    for r in rows:
        cells = []
        for s in subsets:
            m = r["metrics"][s]
            cells += [f"{100 * m['miou']:.1f}" if not math.isnan(m["miou"]) else "-",
                      f"{100 * m['macc']:.1f}" if not math.isnan(m["macc"]) else "-"]
        body += f"| {r['method']} | {r['scene']} | {r['split']} | " + " | ".join(cells) + " |\n"
    return head + body
