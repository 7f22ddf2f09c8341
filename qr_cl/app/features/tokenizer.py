"""CLIP's byte-level BPE tokenizer (Radford et al. 2021), reading the merges file that ships with
OpenAI's ``clip`` and with ``open_clip_torch``: ``bpe_simple_vocab_16e6.txt.gz`` (MIT). qr-cl
does not ship it and never downloads it: :func:`find_vocabulary` looks for it and says where.

Text is cleaned (HTML entities, whitespace, lower case; ftfy's repair of mis-decoded text is left
out, which changes nothing for well-formed text), split by CLIP's pattern (contractions,
letter runs, single digits, other symbol runs), each piece's UTF-8 bytes mapped to printable
characters and merged by rank; token ids are the 256 byte symbols, the same with an end-of-word
mark, the merges in order, then start- and end-of-text.
"""
from __future__ import annotations

import gzip
import html
import importlib.util
import os
from functools import lru_cache
from pathlib import Path

import torch

from .errors import FeaturesError

VOCABULARY_FILE = "bpe_simple_vocab_16e6.txt.gz"
#: Merges CLIP uses (the file has a few more).
MERGES = 49152 - 256 - 2
#: Packages that ship the vocabulary beside their modules.
_PACKAGES = ("open_clip", "clip")


def find_vocabulary(explicit: str | os.PathLike | None, weights: str | os.PathLike) -> Path:
    """The BPE vocabulary: ``explicit`` (``--clip-vocab``), else :data:`VOCABULARY_FILE`
    beside ``weights``, else the copy of an installed ``open_clip`` or ``clip`` package (found
    without importing it). FeaturesError naming what is missing."""
    if explicit is not None:
        path = Path(explicit)
        if not path.is_file():
            raise FeaturesError(f"{path}: no such BPE vocabulary file (--clip-vocab)")
        return path
    candidates = [Path(weights).parent / VOCABULARY_FILE]
    for name in _PACKAGES:
        spec = importlib.util.find_spec(name)
        if spec is not None and spec.submodule_search_locations:
            candidates += [Path(p) / VOCABULARY_FILE for p in spec.submodule_search_locations]
    for path in candidates:
        if path.is_file():
            return path
    raise FeaturesError(f"{VOCABULARY_FILE}: CLIP's BPE vocabulary is needed to encode text and was not found "
                        f"beside {weights} nor in an installed open_clip or clip package; pass --clip-vocab FILE "
                        "(it ships in open_clip_torch's wheel: pip install --no-deps open_clip_torch)")


@lru_cache(maxsize=1)
def byte_symbols() -> dict[int, str]:
    """Each byte's printable character, printable Latin-1 bytes first (mapped to themselves), then
    the others (to code points from 256 on): the order of the first 256 token ids."""
    printable = [*range(ord("!"), ord("~") + 1), *range(ord("¡"), ord("¬") + 1), *range(ord("®"), ord("ÿ") + 1)]
    others = [b for b in range(256) if b not in printable]
    table = {b: chr(b) for b in printable}
    table.update({b: chr(256 + i) for i, b in enumerate(others)})
    return table


class ClipTokenizer:
    """Texts -> [B, context] int64 token ids (module docstring)."""

    def __init__(self, vocabulary: str | os.PathLike):
        import regex  # the features extra: Unicode letter/number classes

        path = Path(vocabulary)
        try:
            lines = gzip.decompress(path.read_bytes()).decode("utf-8").split("\n")
        except (OSError, EOFError, UnicodeDecodeError) as exc:
            raise FeaturesError(f"{path}: not a gzip BPE vocabulary ({exc})") from None
        merges = [tuple(line.split()) for line in lines[1:MERGES + 1] if line.strip()]
        if any(len(m) != 2 for m in merges):
            raise FeaturesError(f"{path}: not a BPE vocabulary (lines of two symbols expected)")
        symbols = list(byte_symbols().values())
        vocab = symbols + [s + "</w>" for s in symbols] + ["".join(m) for m in merges]
        vocab += ["<|startoftext|>", "<|endoftext|>"]
        self.ids = {token: i for i, token in enumerate(vocab)}
        self.ranks = {m: i for i, m in enumerate(merges)}
        self.start, self.end = self.ids["<|startoftext|>"], self.ids["<|endoftext|>"]
        self.pattern = regex.compile(r"<\|startoftext\|>|<\|endoftext\|>|'s|'t|'re|'ve|'m|'ll|'d|[\p{L}]+|[\p{N}]"
                                     r"|[^\s\p{L}\p{N}]+", regex.IGNORECASE)
        self.cache: dict[str, list[int]] = {}

    @property
    def size(self) -> int:
        """Number of token ids."""
        return len(self.ids)

    def _merge(self, piece: str) -> list[int]:
        if piece in self.cache:
            return self.cache[piece]
        word = list(piece[:-1]) + [piece[-1] + "</w>"]
        while len(word) > 1:
            pairs = [(self.ranks.get(p, len(self.ranks)), i, p) for i, p in enumerate(zip(word, word[1:]))]
            rank, _, best = min(pairs)
            if rank == len(self.ranks):
                break
            merged, i = [], 0
            while i < len(word):
                if i < len(word) - 1 and (word[i], word[i + 1]) == best:
                    merged.append(word[i] + word[i + 1])
                    i += 2
                else:
                    merged.append(word[i])
                    i += 1
            word = merged
        self.cache[piece] = [self.ids[w] for w in word]
        return self.cache[piece]

    def encode(self, text: str) -> list[int]:
        """The BPE ids of ``text`` (without start and end tokens)."""
        text = " ".join(html.unescape(html.unescape(text)).split()).strip().lower()
        symbols = byte_symbols()
        ids = []
        for piece in self.pattern.findall(text):
            ids += self._merge("".join(symbols[b] for b in piece.encode("utf-8")))
        return ids

    def __call__(self, texts: list[str], context: int) -> torch.Tensor:
        """[len(texts), context] int64: start, ids, end (cut to fit), zeros."""
        out = torch.zeros(len(texts), context, dtype=torch.int64)
        for row, text in enumerate(texts):
            ids = [self.start, *self.encode(text)][:context - 1] + [self.end]
            out[row, :len(ids)] = torch.tensor(ids)
        return out
