"""Study: the main run's segmentation of the held-out room: per-class IoU, the confusion matrix
(a picture with the class names) and the segmentation pictures."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluation.metrics import SUBSETS, confusion_matrix, miou_macc
from ..evaluation.scoring import predict
from ..evaluation.visuals import PANEL_SIZE, write_visuals
from ..images import plt
from ..scenes.folders import SceneData
from ..scenes.views import room_overview_cameras


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


def segmentation_study(held: SceneData, features: np.ndarray, gt: np.ndarray, out: Path, label: str) -> dict:
    """Per-class IoU/accuracy over the 19 classes of per-Gaussian ``features`` [N,C] against
    ``gt`` [N], ``confusion.png`` and the pictures of :func:`write_visuals` from two views over
    the room (into ``out``/images). Returns {"label", "per_class": [{"class", "iou", "acc",
    "support"}], "files"}."""
    table = held.classes.subset(SUBSETS[19])
    pred = predict(features, table)
    scores = miou_macc(pred, gt, table.ids)["per_class"]
    per_class = [{"class": name, "iou": 100 * scores[int(c)]["iou"], "acc": 100 * scores[int(c)]["acc"],
                  "support": scores[int(c)]["support"]} for c, name in zip(table.ids, table.names)
                 if int(c) in scores]
    confusion = out / "confusion.png"
    plot_confusion(confusion_matrix(pred, gt, table.ids), list(table.names), confusion,
                   f"{label}: held-out room, 19 classes")
    images = write_visuals(held, features, gt, out / "images", room_overview_cameras(held.gaussians, *PANEL_SIZE))
    return {"label": label, "per_class": per_class,
            "files": [str(p.relative_to(out)) for p in [confusion, *images] if p.suffix == ".png"]}
