"""Real CLIP text embeddings of the ScanNet200 class names, shipped as package data (MIT; see
LICENSE and SOURCE.md beside this file), and :class:`ClassTable`, a table of classes built from
them by name.

The embeddings are OpenAI CLIP ViT-B/32's of the prompt "a {name}" (float16 [200, 512], unit rows).
Real CLIP classes are far from orthogonal (chair and office chair, table and desk, wall and door
are close), which is what open-vocabulary segmentation has to cope with.
"""
from __future__ import annotations

import difflib
import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

#: Names of the ScanNet evaluation classes that the table spells differently.
ALIASES = {"sofa": "couch", "books": "book", "television": "tv"}


@lru_cache(maxsize=None)
def scannet200() -> tuple[tuple[str, ...], np.ndarray]:
    """(the 200 class names, their text embeddings [200, 512] float32 with unit rows)."""
    root = resources.files(__name__)
    names = tuple(json.loads((root / "names.json").read_text())["names"])
    with (root / "scannet200_clip_vitb32.npy").open("rb") as f:
        table = np.load(f).astype(np.float32)
    table /= np.linalg.norm(table, axis=1, keepdims=True)
    if table.shape != (len(names), 512):
        raise ValueError(f"the shipped CLIP table is {table.shape}, expected ({len(names)}, 512)")
    return names, table


@dataclass(frozen=True)
class ClassTable:
    """Classes by name and their CLIP text embeddings: ``names`` [K] and ``embeddings`` [K, 512]
    float32 unit rows, in the order asked for."""

    names: tuple[str, ...]
    embeddings: np.ndarray

    @classmethod
    def from_names(cls, names) -> ClassTable:
        """The table of ``names`` (ScanNet200 names, or an alias of :data:`ALIASES`); KeyError
        naming each unknown name with its closest known ones."""
        known, table = scannet200()
        index = {name: i for i, name in enumerate(known)}
        rows, unknown = [], []
        for name in names:
            key = ALIASES.get(name, name)
            if key in index:
                rows.append(index[key])
            else:
                close = difflib.get_close_matches(name, known, n=3, cutoff=0.6)
                unknown.append(f"{name!r} (closest: {', '.join(close) if close else 'none'})")
        if unknown:
            raise KeyError("not in the ScanNet200 CLIP table: " + "; ".join(unknown))
        return cls(tuple(names), table[rows])

    def similarity(self) -> np.ndarray:
        """Cosine similarities [K, K] between the classes' text embeddings."""
        return self.embeddings @ self.embeddings.T
