"""Study: the segmentation of the held-out room by the main run and the other models of Table 2:
per-class IoU (with each class's share of the labelled Gaussians and the classes the main run
leaves below the bar), the main run's confusion matrix (a picture with the class names), its
segmentation pictures and the models' predictions side by side."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluation.metrics import SUBSETS, confusion_matrix, miou_macc
from ..evaluation.scoring import predict
from ..evaluation.visuals import PANEL_SIZE, write_comparison, write_visuals
from ..images import plt
from ..scenes.folders import SceneData
from ..scenes.views import room_overview_cameras

#: The bar of the quick plan: every class above MIN_SHARE of the labelled Gaussians gets an IoU
#: (in %) above MIN_IOU through the main run.
MIN_SHARE, MIN_IOU = 0.01, 10.0


def plot_confusion(counts: np.ndarray, names: list[str], path: Path, title: str) -> None:
    """The confusion matrix ``counts`` [K,K] (row = ground truth, column = prediction) normalised
    per row, as a picture with the class ``names``; rows without support are left blank."""
    support = counts.sum(1, keepdims=True)
    share = np.where(support > 0, counts / np.maximum(support, 1), np.nan)
    fig, ax = plt.subplots(figsize=(8.5, 7.5))
    im = ax.imshow(share, vmin=0, vmax=1, cmap="viridis")
    ax.set_xticks(range(len(names)), names, rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(len(names)), [f"{n} ({int(s)})" for n, s in zip(names, support[:, 0])], fontsize=8)
    for i, j in zip(*np.nonzero(np.nan_to_num(share) >= 0.1)):
        ax.text(j, i, f"{share[i, j]:.2f}", ha="center", va="center", fontsize=6,
                color="black" if share[i, j] > 0.6 else "white")
    ax.set(xlabel="predicted class", ylabel="ground truth (labelled Gaussians)", title=title)
    fig.colorbar(im, ax=ax, fraction=0.04, label="share of the row")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def segmentation_study(held: SceneData, models: dict[str, np.ndarray], gt: np.ndarray, out: Path,
                       label: str) -> dict:
    """Per-class IoU/accuracy over the 19 classes of each model's per-Gaussian features [N,C]
    (``models``: name -> features, the main run first, titled ``label``) against ``gt`` [N], the
    main run's ``confusion.png`` and pictures (:func:`write_visuals`) and the models side by side
    (:func:`write_comparison`), from two views over the room (into ``out``/images). Returns
    {"label", "models" (the names), "per_class": [{"class", "iou" and "acc" (the main run's),
    "models": {name: IoU}, "support", "share"}], "min_share", "min_iou", "below_bar" (the classes
    above ``MIN_SHARE`` the main run leaves at or under ``MIN_IOU``), "files"}."""
    table = held.classes.subset(SUBSETS[19])
    preds = {name: predict(features, table) for name, features in models.items()}
    scores = {name: miou_macc(pred, gt, table.ids)["per_class"] for name, pred in preds.items()}
    main = next(iter(models))
    total = max(int(np.isin(gt, table.ids).sum()), 1)
    per_class = [{"class": name, "iou": 100 * scores[main][int(c)]["iou"], "acc": 100 * scores[main][int(c)]["acc"],
                  "models": {m: 100 * scores[m][int(c)]["iou"] for m in models},
                  "support": scores[main][int(c)]["support"], "share": scores[main][int(c)]["support"] / total}
                 for c, name in zip(table.ids, table.names) if int(c) in scores[main]]
    below = [c["class"] for c in per_class if c["share"] > MIN_SHARE and c["iou"] <= MIN_IOU]
    confusion = out / "confusion.png"
    plot_confusion(confusion_matrix(preds[main], gt, table.ids), list(table.names), confusion,
                   f"{label}: held-out room, 19 classes")
    cams = room_overview_cameras(held.gaussians, *PANEL_SIZE)
    images = write_visuals(held, models[main], gt, out / "images", cams)
    images += write_comparison(held, {(label if m == main else m): f for m, f in models.items()}, gt,
                               out / "images", cams)
    return {"label": label, "models": list(models), "per_class": per_class, "min_share": MIN_SHARE,
            "min_iou": MIN_IOU, "below_bar": below,
            "files": [str(p.relative_to(out)) for p in [confusion, *images] if p.suffix == ".png"]}
