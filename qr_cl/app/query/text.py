"""Query text -> text embedding, looked up in this order:

1. the scene's ``classes.json`` (its own ``text_feature`` rows; names matched without case),
2. the shipped real CLIP ViT-B/32 table of the ScanNet200 names (:mod:`qr_cl.app.vocab`, with
   its aliases), when the scene's features are 512-D and its classes.json (if any) agrees with
   the table on the names both have (so the features are in the table's text space),
3. an optional text encoder (:func:`open_clip_encoder`: OpenCLIP with weights from a local file;
   nothing is downloaded), for any other text.

Text none of them knows raises :class:`UnknownQueryError` naming the closest known names.

The shipped table holds CLIP ViT-B/32 embeddings of the prompt "a {name}": it is meaningful only
for features in that model's space (GS-Net trained on ViT-B/32 LangSplat features, or the
synthetic rooms, whose classes.json holds the table's own rows). The orthogonal-prototype rooms'
classes.json disagrees with the table, so only its own rows are used there.
"""
from __future__ import annotations

import difflib
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..scenes.folders import ClassTable, unit_rows
from ..vocab import ALIASES, scannet200

#: A text encoder: Q texts -> [Q, C] float embeddings (any norm; rows are normalised here).
TextEncoder = Callable[[Sequence[str]], np.ndarray]

#: Where a text embedding came from (:attr:`TextEmbedding.source`).
SCENE_CLASSES, SHIPPED_TABLE, ENCODER = "classes.json", "ScanNet200 CLIP table", "text encoder"
#: Mean cosine between a scene's classes.json rows and the shipped table's rows of the same names
#: from which both are taken to be in one text space (one CLIP model).
SAME_SPACE_COSINE = 0.8


class QueryError(ValueError):
    """Query input that cannot be used; the message says what is wrong."""


class UnknownQueryError(QueryError):
    """Query text that no source knows; the message names the closest known names."""


@dataclass(frozen=True)
class TextEmbedding:
    """One query: its ``text``, the ``embedding`` [C] float32 unit row and its ``source`` (one of
    :data:`SCENE_CLASSES`, :data:`SHIPPED_TABLE`, :data:`ENCODER`)."""

    text: str
    embedding: np.ndarray
    source: str


def normalise(text: str) -> str:
    """The key a text is matched by: lower case, single spaces, no surrounding space."""
    return " ".join(text.lower().split())


class TextLookup:
    """Looks query texts up for features of ``dim`` channels: the scene's ``classes`` (or None),
    the shipped ScanNet200 table (512-D features only), then ``encoder`` (or None)."""

    def __init__(self, dim: int, classes: ClassTable | None = None, encoder: TextEncoder | None = None):
        self.dim = dim
        self.classes = classes if classes is not None and len(classes.names) else None
        self.encoder = encoder
        self._scene = {normalise(n): i for i, n in enumerate(classes.names)} if self.classes else {}
        if self.classes is not None and self.classes.text_features.shape[1] != dim:
            raise QueryError(f"classes.json text features are {self.classes.text_features.shape[1]}-D, "
                             f"the scene's features {dim}-D")
        self._table_names, self._table = scannet200() if self._table_applies() else ((), None)
        self._table_index = {n: i for i, n in enumerate(self._table_names)}

    def _table_applies(self) -> bool:
        """Whether the shipped table is in the space of the scene's features: they are as wide,
        and the scene's classes.json rows of names the table also has (if any) agree with the
        table's (mean cosine >= :data:`SAME_SPACE_COSINE`; simulated or other models' text
        features do not)."""
        names, table = scannet200()
        if table.shape[1] != self.dim:
            return False
        index = {n: i for i, n in enumerate(names)}
        shared = [(i, index[ALIASES.get(k, k)]) for k, i in self._scene.items() if ALIASES.get(k, k) in index]
        if not shared:
            return True
        rows, table_rows = zip(*shared)
        agree = np.sum(unit_rows(self.classes.text_features[list(rows)]) * table[list(table_rows)], 1)
        return bool(agree.mean() >= SAME_SPACE_COSINE)

    def known_names(self) -> list[str]:
        """Every name found without the encoder: the scene's classes, then the shipped table's."""
        return list(dict.fromkeys([*(self.classes.names if self.classes else []), *self._table_names]))

    def _keys(self, text: str) -> list[str]:
        key = normalise(text)
        back = [name for name, alias in ALIASES.items() if alias == key]
        return [key] + ([ALIASES[key]] if key in ALIASES else []) + back

    def __call__(self, text: str) -> TextEmbedding:
        """The embedding of ``text`` (module docstring for the order); UnknownQueryError naming
        the closest known names when no source knows it."""
        if not normalise(text):
            raise QueryError("an empty query: type a class name or a phrase")
        keys = self._keys(text)
        for key in keys:
            if key in self._scene:
                return TextEmbedding(text, unit_rows(self.classes.text_features[self._scene[key]]), SCENE_CLASSES)
        for key in keys:
            if key in self._table_index:
                return TextEmbedding(text, self._table[self._table_index[key]], SHIPPED_TABLE)
        if self.encoder is not None:
            return TextEmbedding(text, self.encode([text])[0], ENCODER)
        known = self.known_names()
        close = difflib.get_close_matches(normalise(text), [normalise(n) for n in known], 5, 0.6)
        if close:
            hint = f"closest: {', '.join(close)}"
        elif known:
            hint = f"known: {', '.join(known[:12])}" + (", ..." if len(known) > 12 else "")
        else:
            hint = "no class names are known for this scene"
        where = "the scene's classes.json" + (" or the ScanNet200 CLIP table" if self._table is not None else "")
        raise UnknownQueryError(f"unknown query {text!r}: not in {where} ({hint}); arbitrary text needs "
                                "a text encoder (--clip-weights)")

    def encode(self, texts: Sequence[str]) -> np.ndarray:
        """[Q, dim] unit rows of the encoder's embeddings of ``texts``; QueryError when there is no
        encoder or its embeddings have another width."""
        if self.encoder is None:
            raise QueryError("no text encoder (--clip-weights) to encode " + ", ".join(map(repr, texts)))
        rows = np.asarray(self.encoder(list(texts)), np.float32)
        if rows.shape != (len(texts), self.dim):
            raise QueryError(f"the text encoder returned {rows.shape} embeddings for {len(texts)} texts; "
                             f"the scene's features are {self.dim}-D")
        return unit_rows(rows)

    def vocabulary(self) -> np.ndarray:
        """[K, dim] unit rows of the class vocabulary: the scene's classes when it has a
        classes.json, else the shipped table (empty [0, dim] when neither applies)."""
        if self.classes is not None:
            return unit_rows(self.classes.text_features)
        if self._table is not None:
            return self._table
        return np.zeros((0, self.dim), np.float32)


def open_clip_encoder(weights: str | os.PathLike, model: str = "ViT-B-32") -> TextEncoder:
    """An OpenCLIP text encoder of architecture ``model`` with the weights of the local file
    ``weights`` (nothing is downloaded: the Hugging Face hub is set offline first). Texts are
    encoded as given. QueryError when open_clip is not installed (``pip install 'qr-cl[clip]'``)
    or the file is missing."""
    path = Path(weights)
    if not path.is_file():
        raise QueryError(f"{path}: no such CLIP weights file (--clip-weights)")
    os.environ["HF_HUB_OFFLINE"] = "1"
    try:
        import open_clip  # optional extra: qr-cl[clip]
    except ImportError:
        raise QueryError("--clip-weights needs open_clip: pip install 'qr-cl[clip]'") from None
    import torch

    net = open_clip.create_model(model, pretrained=str(path))
    net.eval()
    tokenizer = open_clip.get_tokenizer(model)

    def encode(texts: Sequence[str]) -> np.ndarray:
        with torch.no_grad():
            return net.encode_text(tokenizer(list(texts))).float().numpy()
    return encode
