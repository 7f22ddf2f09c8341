"""Per-Gaussian scores of a query: relevancy (the default) or cosine similarity.

- ``cosine``: the cosine similarity, in [-1, 1], between each Gaussian's feature and the query's
  text embedding.
- ``relevancy``: LERF's and LangSplat's relevancy, ``min_j softmax([s_q, s_j] / tau)[0]`` over
  negative texts j, where s is the cosine of the Gaussian's feature with a text and tau = 0.1
  (their scale 10). That minimum equals ``sigmoid((s_q - max_j s_j) / tau)``: in [0, 1], 0.5 where
  the query is exactly as close as the closest negative. The negatives are LangSplat's canonical
  phrases ("object", "things", "stuff", "texture") when a text encoder is available to embed them;
  otherwise (the shipped ScanNet200 table has no such phrases) the other classes of the scene's
  vocabulary (its classes.json, else the ScanNet200 table), so that relevancy > 0.5 where the
  query beats every other class, i.e. where ``qr-cl eval`` would predict it.
"""
from __future__ import annotations

import numpy as np

from ..scenes.folders import unit_rows
from .text import TextEmbedding, TextLookup

#: The negative phrases of LERF and LangSplat's relevancy (used with a text encoder).
CANONICAL_PHRASES = ("object", "things", "stuff", "texture")
#: Softmax temperature of the relevancy (LERF/LangSplat multiply cosines by 10).
TEMPERATURE = 0.1
#: Score methods (module docstring).
METHODS = ("relevancy", "cosine")
#: Negatives closer than this cosine to the query are the query itself and are left out.
SAME_TEXT_COSINE = 0.9999


def negatives(lookup: TextLookup, query: TextEmbedding) -> np.ndarray:
    """The negative texts [M,C] (unit rows) of ``query``'s relevancy (module docstring): the
    canonical phrases embedded by the lookup's encoder, else the vocabulary without the query."""
    if lookup.encoder is not None:
        return lookup.encode(CANONICAL_PHRASES)
    vocab = lookup.vocabulary()
    return vocab[vocab @ query.embedding < SAME_TEXT_COSINE]


def relevancy(features: np.ndarray, query: np.ndarray, negative: np.ndarray,
              temperature: float = TEMPERATURE) -> np.ndarray:
    """Relevancy [N] in [0, 1] of unit-row ``features`` [N,C] for the unit ``query`` [C] against
    the unit ``negative`` rows [M,C]: ``sigmoid((s_q - max_j s_j) / temperature)`` with s the
    cosines (module docstring); with no negatives, ``sigmoid(s_q / temperature)``."""
    s_q = features @ query
    s_neg = (features @ negative.T).max(1) if len(negative) else np.zeros_like(s_q)
    return (1 / (1 + np.exp(-(s_q - s_neg).astype(np.float64) / temperature))).astype(np.float32)


def score(features: np.ndarray, lookup: TextLookup, query: TextEmbedding, method: str = "relevancy") -> np.ndarray:
    """Per-Gaussian score [N] float32 of ``query`` for ``features`` [N,C] (any norm): ``method``
    "relevancy" in [0, 1] or "cosine" in [-1, 1] (module docstring)."""
    if method not in METHODS:
        raise ValueError(f"score method {method!r}: choose one of {METHODS}")
    f = unit_rows(features)
    if method == "cosine":
        return (f @ query.embedding).astype(np.float32)
    return relevancy(f, query.embedding, negatives(lookup, query))


def score_range(values: np.ndarray) -> tuple[float, float]:
    """The (low, high) values a colour map of the scores ``values`` [N] spans: their 1st..99th
    percentile, so heatmaps show where a query is most relevant in this scene (relative, as
    LangSplat's normalised maps; the .npy keeps the raw scores)."""
    lo, hi = np.percentile(values, [1, 99]) if len(values) else (0.0, 1.0)
    return float(lo), float(max(hi, lo + 1e-6))
