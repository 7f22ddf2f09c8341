"""Selections kept between calls: :class:`SelectionCache` (bounded in device bytes) and the
digest :func:`selection_key` of what determines a Selection."""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from typing import Callable, Hashable

import numpy as np

from ..stages import BackwardIndex, Selection


def selection_key(*arrays_and_values) -> str:
    """A digest of the arrays (bytes, shape, dtype) and values that determine a Selection:
    Gaussians, camera, image size, near/far, sampler, K and rays. Hashes every byte of the arrays,
    so its cost grows with their size."""
    h = hashlib.blake2b(digest_size=20)
    for item in arrays_and_values:
        if isinstance(item, np.ndarray):
            h.update(str((item.shape, item.dtype.str)).encode())
            h.update(np.ascontiguousarray(item).data)
        else:
            h.update(repr(item).encode())
    return h.hexdigest()


class SelectionCache:
    """Selections (with their RasterPlans) kept on the device between calls, at most ``max_bytes``
    of device memory in all, under any hashable key: :func:`selection_key`'s digest
    (:func:`qr_cl.rasterize`), or e.g. (scene, view, sampler, K) (training's whole-view selections).

    Selections depend on geometry, camera, sampler and K only, so training can reuse one per view
    every epoch. Each entry keeps, beside its Selection, the selection's
    :class:`~qr_cl.stages.BackwardIndex` (what backwards of it make once and share), counted in
    its bytes. :meth:`find` and :meth:`keep` (which evicts the least recently used) serve the
    engine, which makes a selection together with its first blend; :meth:`get_if_room` evicts
    nothing.
    A Selection larger than ``max_bytes`` is returned but not kept. Cache-free rendering (no cache
    passed to :func:`qr_cl.rasterize`) is the default.
    """

    def __init__(self, max_bytes: int) -> None:
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._entries: OrderedDict[Hashable, tuple[Selection, BackwardIndex]] = OrderedDict()
        self._last_size = 0
        self.hits = self.misses = self.refused = 0

    @staticmethod
    def _size(sel: Selection, backward_index: BackwardIndex | None = None) -> int:
        return sel.nbytes + sel.plan.nbytes + (0 if backward_index is None else backward_index.nbytes)

    @property
    def nbytes(self) -> int:
        """Device bytes held now."""
        return sum(self._size(sel, index) for sel, index in self._entries.values())

    def _hit(self, key: Hashable) -> Selection | None:
        """The Selection kept under ``key`` (now the most recently used), counting the hit or miss."""
        if key in self._entries:
            self.hits += 1
            self._entries.move_to_end(key)
            return self._entries[key][0]
        self.misses += 1
        return None

    def _make(self, make: Callable[[], Selection]) -> tuple[Selection, int]:
        sel = make()
        self._last_size = self._size(sel)
        return sel, self._last_size

    def find(self, key: Hashable) -> tuple[Selection, BackwardIndex] | None:
        """The Selection cached under ``key`` and its backward index (now the most recently used),
        or None; counted as a hit or a miss."""
        sel = self._hit(key)
        return None if sel is None else self._entries[key]

    def keep(self, key: Hashable, sel: Selection) -> BackwardIndex:
        """Cache ``sel`` under ``key``, evicting the least recently used until it fits (a Selection
        larger than ``max_bytes`` is not kept); the :class:`~qr_cl.stages.BackwardIndex` to pass
        to its backwards (kept with it, or made for a selection not kept)."""
        index = BackwardIndex()
        size = self._last_size = self._size(sel)
        if size <= self.max_bytes:
            while self._entries and self.nbytes + size > self.max_bytes:
                self._entries.popitem(last=False)
            self._entries[key] = (sel, index)
        return index

    def get_if_room(self, key: Hashable, make: Callable[[], Selection]) -> Selection | None:
        """The Selection cached under ``key``; else, while a Selection the size of the last one
        made would still fit, ``make()``'s (cached if it fits, returned either way); else None.
        Nothing is evicted, so nothing kept is made twice: keys drawn at random (training's views)
        would otherwise evict each other, and the caller makes something cheaper instead."""
        sel = self._hit(key)
        if sel is not None:
            return sel
        if self.nbytes + self._last_size > self.max_bytes:
            self.refused += 1
            return None
        sel, size = self._make(make)
        if self.nbytes + size <= self.max_bytes:
            self._entries[key] = (sel, BackwardIndex())
        else:
            self.refused += 1
        return sel

    def __len__(self) -> int:
        return len(self._entries)
