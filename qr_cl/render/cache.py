"""Selections kept between calls: :class:`SelectionCache` (LRU, bounded in device bytes) and the
digest :func:`selection_key` of what determines a Selection."""
from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np

from ..stages.select import Selection


def selection_key(*arrays_and_values) -> str:
    """A digest of the arrays (bytes, shape, dtype) and values that determine a Selection:
    Gaussians, camera, image size, near/far, sampler, K and rays. ~2 ms for 50k Gaussians."""
    h = hashlib.blake2b(digest_size=20)
    for item in arrays_and_values:
        if isinstance(item, np.ndarray):
            h.update(str((item.shape, item.dtype.str)).encode())
            h.update(np.ascontiguousarray(item).data)
        else:
            h.update(repr(item).encode())
    return h.hexdigest()


class SelectionCache:
    """Selections (with their RasterPlans) kept on the device between calls, least recently used
    evicted first, at most ``max_bytes`` of device memory in all.

    Selections depend on geometry, camera, sampler and K only, so training can reuse one per view
    every epoch. A Selection larger than ``max_bytes`` is returned but not kept. Cache-free
    rendering (no cache passed to :func:`qr_cl.rasterize`) is the default.
    """

    def __init__(self, max_bytes: int) -> None:
        if max_bytes <= 0:
            raise ValueError(f"max_bytes must be positive, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._entries: OrderedDict[str, Selection] = OrderedDict()
        self.hits = self.misses = 0

    @staticmethod
    def _size(sel: Selection) -> int:
        return sel.nbytes + sel.plan.nbytes

    @property
    def nbytes(self) -> int:
        """Device bytes held now."""
        return sum(self._size(sel) for sel in self._entries.values())

    def get(self, key: str, make) -> Selection:
        """The Selection cached under ``key``, or ``make()``'s, which is then cached."""
        if key in self._entries:
            self.hits += 1
            self._entries.move_to_end(key)
            return self._entries[key]
        self.misses += 1
        sel = make()
        size = self._size(sel)
        if size <= self.max_bytes:
            while self._entries and self.nbytes + size > self.max_bytes:
                self._entries.popitem(last=False)
            self._entries[key] = sel
        return sel

    def __len__(self) -> int:
        return len(self._entries)
