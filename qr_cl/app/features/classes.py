"""``classes.json`` from class names, with the text features of the same CLIP as the masks'.

Names are encoded with the prompt ``"a {name}"`` by the weights' text tower (which needs CLIP's
BPE vocabulary, :mod:`.tokenizer`). For a ViT-B/32 the shipped ScanNet200 table (OpenAI
ViT-B/32, the same prompt) gives the rows of the names it has: when the vocabulary is found the
table is used only if the weights' text tower agrees with it (other ViT-B/32 weights are encoded
instead), without it the table is trusted. The file records the encoder (model name, weights
file name and sha256, prompt) so ``qr-cl query`` can refuse another encoder's text features.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from ..query.text import SAME_SPACE_COSINE
from ..vocab import ALIASES, scannet200
from .clip_model import Clip
from .errors import FeaturesError
from .store import write_atomic
from .tokenizer import ClipTokenizer
from .weights import file_sha256

PROMPT = "a {}"
#: Models whose text space the shipped table is in.
TABLE_MODELS = ("ViT-B-32", "ViT-B-32-quickgelu")


def read_class_names(value: str) -> list[str]:
    """Class names from ``--classes``: a file (one name per line, or a JSON list) or a
    comma-separated list; FeaturesError for none or a repeated name."""
    path = Path(value)
    if path.is_file():
        text = path.read_text()
        try:
            names = json.loads(text) if text.lstrip().startswith("[") else text.splitlines()
        except json.JSONDecodeError as exc:
            raise FeaturesError(f"{path}: not a JSON list of class names ({exc})") from None
    else:
        names = value.split(",")
    names = [str(n).strip() for n in names if str(n).strip()]
    if not names:
        raise FeaturesError(f"--classes {value!r}: no class names")
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise FeaturesError(f"--classes {value!r}: repeated names {', '.join(repeated)}")
    return names


def encode_texts(clip: Clip, tokenizer: ClipTokenizer, texts: list[str]) -> np.ndarray:
    """[len(texts), E] unit text embeddings of ``texts`` (on ``clip``'s device)."""
    if tokenizer.size > clip.arch.vocab:
        raise FeaturesError(f"the BPE vocabulary gives {tokenizer.size} tokens but the weights' text tower has "
                            f"{clip.arch.vocab}: another vocabulary (--clip-vocab)")
    device = clip.visual.proj.device
    with torch.no_grad():
        rows = clip.encode_text(tokenizer(texts, clip.arch.context).to(device)).float().cpu().numpy()
    return rows / np.maximum(np.linalg.norm(rows, axis=1, keepdims=True), 1e-12)


def _table_rows(names: list[str]) -> dict[str, np.ndarray]:
    known, table = scannet200()
    index = {n: i for i, n in enumerate(known)}
    return {n: table[index[ALIASES.get(n.lower(), n.lower())]] for n in names
            if ALIASES.get(n.lower(), n.lower()) in index}


def class_features(clip: Clip, tokenizer: ClipTokenizer | None, names: list[str],
                   vocabulary_error: FeaturesError | None) -> tuple[np.ndarray, list[str]]:
    """([K, E] unit text features, the source of each: "encoder" or "ScanNet200 table") of
    ``names`` (module docstring). ``tokenizer`` is None when the vocabulary was not found
    (``vocabulary_error`` says why, raised when a name needs the encoder)."""
    if not clip.arch.text_width:
        raise FeaturesError("the CLIP weights have no text tower: --classes needs one")
    table = _table_rows(names) if clip.arch.name in TABLE_MODELS else {}
    if table and tokenizer is not None:
        shared = list(table)
        agree = float(np.mean(np.sum(encode_texts(clip, tokenizer, [PROMPT.format(n) for n in shared])
                                     * np.stack([table[n] for n in shared]), 1)))
        if agree < SAME_SPACE_COSINE:
            print(f"the weights' text tower disagrees with the shipped ViT-B/32 table (mean cosine {agree:.2f}): "
                  "encoding every name")
            table = {}
    rest = [n for n in names if n not in table]
    if rest and tokenizer is None:
        raise vocabulary_error
    encoded = dict(zip(rest, encode_texts(clip, tokenizer, [PROMPT.format(n) for n in rest]))) if rest else {}
    rows = np.stack([table[n] if n in table else encoded[n] for n in names]).astype(np.float32)
    return rows, ["ScanNet200 table" if n in table else "encoder" for n in names]


def encoder_record(clip: Clip, weights: Path) -> dict:
    """The text encoder's identity as ``classes.json`` records it."""
    return {"model": clip.arch.name, "weights": weights.name, "sha256": file_sha256(weights), "prompt": PROMPT}


def write_classes(path: Path, names: list[str], rows: np.ndarray, sources: list[str], encoder: dict) -> None:
    """Write ``classes.json`` (ids 0..K-1 in the order given) atomically; FeaturesError when a
    ``classes.json`` that ``qr-cl features`` did not write is in the way."""
    if path.is_file():
        try:
            ours = "encoder" in json.loads(path.read_text())
        except (json.JSONDecodeError, TypeError):
            ours = False
        if not ours:
            raise FeaturesError(f"{path}: exists and was not written by qr-cl features; move it away to write "
                                "--classes")
    data = {"encoder": encoder, "classes": [{"id": i, "name": n, "source": s, "text_feature": r.tolist()}
                                            for i, (n, s, r) in enumerate(zip(names, sources, rows))]}
    write_atomic(path, lambda fh: fh.write(json.dumps(data).encode()))


def recorded_encoder(path: Path) -> dict | None:
    """The encoder a ``classes.json`` records (None for a file without one, or no file)."""
    try:
        encoder = json.loads(Path(path).read_text()).get("encoder")
    except (OSError, json.JSONDecodeError, AttributeError):
        return None
    return encoder if isinstance(encoder, dict) else None
