"""Numpy twin of blend.cl (:mod:`qr_cl.stages.blend`), in float64."""
from __future__ import annotations

import numpy as np


def blend(ids: np.ndarray, weights: np.ndarray, features: np.ndarray, t_rem: np.ndarray | None = None,
          background=None) -> np.ndarray:
    """image [P,C] = sum_j weights[p,j] features[ids[p,j]] (+ t_rem[p] background), in float64.
    ids [P,L] (-1 = padding), weights [P,L], features [N,C]."""
    f = np.asarray(features, np.float64)
    gathered = f[np.maximum(ids, 0)] * np.where(ids >= 0, weights, 0)[..., None]
    image = gathered.sum(1) if ids.shape[1] else np.zeros((len(ids), f.shape[1]))
    if background is not None:
        image = image + np.asarray(t_rem, np.float64)[:, None] * np.asarray(background, np.float64)[None]
    return image
