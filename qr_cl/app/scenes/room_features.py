"""The simulated CLIP features of a synthetic room: each class's anchor, the image feature of one
mask, and the text feature a class is queried with. Two models (``SyntheticConfig.features``):

- ``"clip"`` (default): a class's anchor is the REAL CLIP ViT-B/32 text embedding of its name
  (:mod:`qr_cl.app.vocab`), so classes are as confusable as in real CLIP (table and desk 0.93,
  wall and picture 0.90, door and window 0.89). A mask's feature is
  ``normalise(anchor + clip_offset * o + clip_noise * n / sqrt(dim))``: ``o`` is one fixed random
  unit vector orthogonal to every class's anchor (the gap between CLIP's image and text
  embeddings: it lowers every image-text cosine alike and favours no class) and ``n`` a fresh
  standard normal vector per mask and level. With the defaults (offset 0.5, noise 3.75) a single mask's feature
  names its own class among the 19 evaluated ones about 70 % of the time (:func:`mask_accuracy`
  measures it; :func:`expected_mask_accuracy` predicts it) and its cosine to its own text
  feature is about 0.26, close to CLIP's image-to-text cosines. A class's text feature is its
  anchor. Below 512 channels (tiny test rooms) the anchors are the table's rows through one fixed
  random projection to ``dim`` channels, renormalised.
- ``"orthogonal"`` (the rooms of earlier releases): a class's anchor is a random unit prototype
  (nearly orthogonal to every other); a mask's feature is ``normalise(prototype + mask_noise *
  u)`` and a class's text feature ``normalise(prototype + text_noise * u')`` with random unit
  ``u``, ``u'``. Any renderer that lands near the right object scores it right.
"""
from __future__ import annotations

import numpy as np

from ..evaluation.metrics import NYU40_NAMES, SUBSETS
from ..vocab import ClassTable
from .procedural import unit
from .room_config import SyntheticConfig

FEATURE_MODELS = ("clip", "orthogonal")


def clip_anchors(dim: int, seed: int) -> dict[int, np.ndarray]:
    """Every class of :data:`NYU40_NAMES` -> its real CLIP text embedding, unit [dim] float64
    (projected by a fixed random matrix seeded by ``seed`` when ``dim`` < 512)."""
    ids = sorted(NYU40_NAMES)
    table = ClassTable.from_names([NYU40_NAMES[c] for c in ids]).embeddings.astype(np.float64)
    if dim > table.shape[1]:
        raise ValueError(f"dim={dim}: the CLIP table has {table.shape[1]} channels")
    if dim < table.shape[1]:
        table = table @ np.random.default_rng(seed).standard_normal((table.shape[1], dim))
    return {c: unit(row) for c, row in zip(ids, table)}


def orthogonal_prototypes(dim: int, seed: int) -> dict[int, np.ndarray]:
    """Every class of :data:`NYU40_NAMES` -> a random unit prototype [dim] float64 (seeded)."""
    rng = np.random.default_rng(seed)
    return {c: unit(rng.standard_normal(dim)) for c in sorted(NYU40_NAMES)}


class RoomFeatures:
    """The feature model of ``cfg`` (module docstring): :meth:`masks` draws image features of
    masks, :meth:`text` gives the text feature of each class."""

    def __init__(self, cfg: SyntheticConfig):
        if cfg.features not in FEATURE_MODELS:
            raise ValueError(f"features={cfg.features!r}: choose one of {FEATURE_MODELS}")
        self.cfg = cfg
        if cfg.features == "clip":
            self.anchors = clip_anchors(cfg.dim, cfg.prototype_seed)
            gap = np.random.default_rng(cfg.prototype_seed + 2).standard_normal(cfg.dim)
            if cfg.dim > len(self.anchors):          # (tiny rooms' anchors may span every channel)
                span, _ = np.linalg.qr(np.stack(list(self.anchors.values())).T)
                gap -= span @ (span.T @ gap)
            self.offset = cfg.clip_offset * unit(gap)
        else:
            self.anchors = orthogonal_prototypes(cfg.dim, cfg.prototype_seed)

    def masks(self, classes: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Image features [M, dim] float32 (unit rows) of M masks of class ids ``classes`` [M]."""
        classes = np.asarray(classes)
        if not len(classes):
            return np.zeros((0, self.cfg.dim), np.float32)
        anchors = np.stack([self.anchors[int(c)] for c in classes])
        noise = rng.standard_normal(anchors.shape)
        if self.cfg.features == "clip":
            feats = anchors + self.offset + self.cfg.clip_noise * noise / np.sqrt(self.cfg.dim)
        else:
            feats = anchors + self.cfg.mask_noise * unit(noise)
        return unit(feats).astype(np.float32)

    def text(self) -> dict[int, np.ndarray]:
        """Every class of :data:`NYU40_NAMES` -> its text feature, unit [dim] float64."""
        if self.cfg.features == "clip":
            return dict(self.anchors)
        rng = np.random.default_rng(self.cfg.prototype_seed + 1)
        return {c: unit(p + self.cfg.text_noise * unit(rng.standard_normal(self.cfg.dim)))
                for c, p in sorted(self.anchors.items())}


def mask_accuracy(features: np.ndarray, classes: np.ndarray, text: dict[int, np.ndarray],
                  subset: int = 19) -> float:
    """Fraction of the masks of an evaluated class whose feature (rows of ``features`` [M, dim],
    class ids ``classes`` [M]) is most cosine-similar to its own class's text feature among the
    ``subset`` evaluated classes (CLIP's zero-shot accuracy on object crops, simulated); NaN
    without such masks."""
    ids = np.asarray(SUBSETS[subset])
    keep = np.isin(classes, ids)
    if not keep.any():
        return float("nan")
    table = np.stack([text[int(c)] for c in ids])
    pred = ids[(np.asarray(features, np.float64)[keep] @ table.T).argmax(1)]
    return float((pred == np.asarray(classes)[keep]).mean())


def expected_mask_accuracy(cfg: SyntheticConfig, per_class: int = 200, seed: int = 0) -> float:
    """:func:`mask_accuracy` of ``per_class`` fresh masks of each evaluated class drawn by the
    model of ``cfg`` (the calibration of its noise)."""
    model = RoomFeatures(cfg)
    classes = np.repeat(np.asarray(SUBSETS[19]), per_class)
    return mask_accuracy(model.masks(classes, np.random.default_rng(seed)), classes, model.text())
