"""Sparse voxel tensors and their kernel maps.

Coordinates are integer voxel indices ``[M, 4]`` = (batch, x, y, z) in units of the finest voxel;
a tensor at stride ``s`` has x, y, z that are multiples of ``s``. Each (batch, x, y, z) is packed
into one int64 key; keys are sorted once per stride level and neighbours are found with
``torch.searchsorted``. Kernel maps (which input feeds which output through which kernel offset)
depend on coordinates only, so a :class:`KernelMapCache` keeps them per stride level and every
tensor derived from the same input shares it (and so can a training loop, since the Gaussians of
GS-Net are frozen).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

COORD_BITS = 17
BATCH_BITS = 12
_COORD_BIAS = 1 << (COORD_BITS - 1)
_COORD_MASK = (1 << COORD_BITS) - 1
#: Largest kernel reach (stride * kernel radius, voxel units) a map may use.
REACH_LIMIT = 1 << 12
#: Largest |x|, |y|, |z| a coordinate may have (voxel units), so that a neighbour key never overflows.
COORD_LIMIT = _COORD_BIAS - REACH_LIMIT - 1
#: Number of scenes one batch may hold.
MAX_BATCH = 1 << BATCH_BITS


def pack_keys(coords: Tensor) -> Tensor:
    """Pack coordinates ``[M, 4]`` int (batch, x, y, z) into int64 keys ``[M]``.

    The packing is monotonic in (batch, x, y, z) lexicographic order and linear in each field,
    so ``pack(c + d) == pack(c) + offset_keys(d)`` while fields stay in range.
    Raises ValueError when a batch index or coordinate is out of range.
    """
    if coords.dim() != 2 or coords.shape[1] != 4:
        raise ValueError(f"coords must have shape [M, 4] (batch, x, y, z), got {list(coords.shape)}")
    if coords.dtype.is_floating_point or coords.dtype == torch.bool:
        raise ValueError(f"coords must be an integer tensor, got {coords.dtype}")
    c = coords.to(torch.int64)
    if c.shape[0]:
        b = c[:, 0]
        if int(b.min()) < 0 or int(b.max()) >= MAX_BATCH:
            raise ValueError(f"batch indices must lie in [0, {MAX_BATCH}), got [{int(b.min())}, {int(b.max())}]")
        span = int(c[:, 1:].abs().max())
        if span > COORD_LIMIT:
            raise ValueError(
                f"voxel coordinates must satisfy |x|, |y|, |z| <= {COORD_LIMIT}, got {span}: "
                "use a larger grid size or recentre the scene"
            )
    xyz = c[:, 1:] + _COORD_BIAS
    return (c[:, 0] << (3 * COORD_BITS)) | (xyz[:, 0] << (2 * COORD_BITS)) | (xyz[:, 1] << COORD_BITS) | xyz[:, 2]


def unpack_keys(keys: Tensor) -> Tensor:
    """Inverse of :func:`pack_keys`: int64 keys ``[M]`` -> coordinates ``[M, 4]`` int64."""
    return torch.stack(
        [
            keys >> (3 * COORD_BITS),
            ((keys >> (2 * COORD_BITS)) & _COORD_MASK) - _COORD_BIAS,
            ((keys >> COORD_BITS) & _COORD_MASK) - _COORD_BIAS,
            (keys & _COORD_MASK) - _COORD_BIAS,
        ],
        dim=1,
    )


def offset_keys(offsets: Tensor) -> Tensor:
    """Key deltas ``[K]`` int64 of spatial offsets ``[K, 3]`` (dx, dy, dz), voxel units."""
    d = offsets.to(torch.int64)
    return (d[:, 0] << (2 * COORD_BITS)) + (d[:, 1] << COORD_BITS) + d[:, 2]


def kernel_offsets(kernel_size: int) -> Tensor:
    """Offsets ``[k^3, 3]`` int64 of a centred odd kernel, lexicographic in (dx, dy, dz), dz fastest.

    Index ``i`` and ``k^3 - 1 - i`` are opposite offsets; the centre has index ``k^3 // 2``.
    """
    r = kernel_size // 2
    axis = torch.arange(-r, r + 1)
    return torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)


@dataclass(frozen=True)
class RowBlock:
    """The pairs of a :class:`KernelMap` whose output rows lie in ``[start, stop)``, offset by offset.

    Those of offset k are ``in_rows[bounds[k]:bounds[k + 1]]`` (input rows) and
    ``out_rows[bounds[k]:bounds[k + 1]]`` (output rows minus ``start``), in the map's pair order;
    the identity offset's pairs stay implicit (rows ``[start, stop)`` of the input).
    """

    start: int
    stop: int
    in_rows: Tensor
    out_rows: Tensor
    bounds: tuple[int, ...]


@dataclass(frozen=True)
class KernelMap:
    """Which input row feeds which output row through which kernel offset.

    ``in_idx[k]`` and ``out_idx[k]`` (int64, equal length) list the pairs of offset ``k``;
    ``identity`` is the offset whose pairs are ``(i, i)`` for every row (stored implicitly,
    ``n_in == n_out``) or None. Derived maps and row blocks are built once and kept on the map.
    """

    in_idx: tuple[Tensor, ...]
    out_idx: tuple[Tensor, ...]
    n_in: int
    n_out: int
    identity: int | None = None
    _derived: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    @property
    def volume(self) -> int:
        """Number of kernel offsets."""
        return len(self.in_idx)

    @property
    def pairs(self) -> int:
        """Number of (input, output) pairs, the identity's ``n_out`` included."""
        if "pairs" not in self._derived:
            self._derived["pairs"] = sum(int(i.numel()) for i in self.in_idx) + (
                self.n_out if self.identity is not None else 0
            )
        return self._derived["pairs"]

    def transposed(self) -> KernelMap:
        """The same pairs with inputs and outputs swapped (the map of the transposed convolution);
        the same object on every call."""
        if "transposed" not in self._derived:
            self._derived["transposed"] = KernelMap(self.out_idx, self.in_idx, self.n_out, self.n_in, self.identity)
        return self._derived["transposed"]

    def row_blocks(self, count: int) -> tuple[RowBlock, ...]:
        """The pairs split into ``count`` blocks of consecutive output rows, each with about the
        same number of pairs (a block may be empty). Depends on the map and ``count`` only, and
        is built once per ``count``."""
        if count < 1:
            raise ValueError(f"count must be >= 1, got {count}")
        key = ("row_blocks", count)
        if key not in self._derived:
            self._derived[key] = self._split_rows(count)
        return self._derived[key]

    def _split_rows(self, count: int) -> tuple[RowBlock, ...]:
        """:meth:`row_blocks`, built: cut where the running count of pairs per output row
        passes each multiple of ``pairs / count``."""
        degree = torch.zeros(self.n_out, dtype=torch.int64)
        for dst in self.out_idx:
            degree += torch.bincount(dst, minlength=self.n_out)
        if self.identity is not None:
            degree += 1
        ends = torch.cumsum(degree, 0)
        targets = torch.tensor([self.pairs * j // count for j in range(1, count)], dtype=torch.int64)
        cuts = [0] + (torch.searchsorted(ends, targets) + 1).clamp_(max=self.n_out).tolist() + [self.n_out]
        inner_cuts = torch.tensor(cuts[1:-1], dtype=torch.int64)
        owner = [torch.bucketize(dst, inner_cuts, right=True) for dst in self.out_idx]
        blocks = []
        empty = torch.empty(0, dtype=torch.int64)
        for b, (start, stop) in enumerate(zip(cuts[:-1], cuts[1:])):
            mine = [o == b for o in owner]
            in_rows = [src[m] for src, m in zip(self.in_idx, mine)]
            bounds = [0] + torch.cumsum(torch.tensor([len(r) for r in in_rows], dtype=torch.int64), 0).tolist()
            out_rows = torch.cat([empty] + [dst[m] - start for dst, m in zip(self.out_idx, mine)])
            blocks.append(RowBlock(start, stop, torch.cat([empty] + in_rows), out_rows, tuple(bounds)))
        return tuple(blocks)


@dataclass(frozen=True)
class _Level:
    coords: Tensor  # [M, 4] int64
    keys: Tensor  # [M] int64, sorted ascending
    order: Tensor | None  # sorted position -> row of coords; None when coords are already sorted

    def lookup(self, query: Tensor) -> Tensor:
        """Row of each query key ``[Q]``, or -1 where absent."""
        m = self.keys.shape[0]
        if m == 0:
            return torch.full_like(query, -1)
        pos = torch.searchsorted(self.keys, query).clamp_(max=m - 1)
        hit = self.keys[pos] == query
        rows = pos if self.order is None else self.order[pos]
        return torch.where(hit, rows, torch.full_like(rows, -1))


class KernelMapCache:
    """Coordinates per stride level and the kernel maps between them, built once and reused."""

    def __init__(self) -> None:
        self._levels: dict[int, _Level] = {}
        self._maps: dict[tuple, KernelMap] = {}

    def register(self, coords: Tensor, stride: int) -> None:
        """Record the coordinates ``[M, 4]`` int64 of stride level ``stride``.

        Registering the same tensor again is free; other coordinates for a known stride raise
        ValueError (a cache belongs to one set of coordinates). Duplicates raise ValueError.
        """
        known = self._levels.get(stride)
        if known is not None:
            if coords is known.coords or torch.equal(coords, known.coords):
                return
            raise ValueError(f"this KernelMapCache already holds other coordinates for stride {stride}")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        if stride > 1 and coords.shape[0] and bool((coords[:, 1:] % stride).any()):
            raise ValueError(f"coordinates of a stride-{stride} tensor must be multiples of {stride}")
        keys = pack_keys(coords)
        order = None
        if keys.shape[0] > 1 and not bool((keys[1:] > keys[:-1]).all()):
            keys, order = torch.sort(keys)
            if bool((keys[1:] == keys[:-1]).any()):
                raise ValueError("coords contain duplicate (batch, x, y, z) rows")
        self._levels[stride] = _Level(coords, keys, order)

    def __len__(self) -> int:
        """Number of kernel maps built so far."""
        return len(self._maps)

    def coords(self, stride: int) -> Tensor:
        """Coordinates ``[M, 4]`` int64 of a registered stride level."""
        if stride not in self._levels:
            raise KeyError(f"no coordinates at stride {stride} in this cache")
        return self._levels[stride].coords

    def submanifold(self, stride: int, kernel_size: int) -> KernelMap:
        """Map of a centred odd ``kernel_size`` convolution whose outputs are its inputs (stride ``stride``).

        Only half of the offsets are searched: a pair (o, i) at offset d is the pair (i, o) at -d.
        """
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"submanifold kernel_size must be odd and >= 1, got {kernel_size}")
        if (kernel_size // 2) * stride > REACH_LIMIT:
            raise ValueError(f"kernel reach {(kernel_size // 2) * stride} exceeds {REACH_LIMIT} voxels")
        key = ("subm", stride, kernel_size)
        if key not in self._maps:
            level = self._levels[stride]
            offsets = kernel_offsets(kernel_size) * stride
            deltas = offset_keys(offsets)
            volume = offsets.shape[0]
            centre = volume // 2
            in_idx: list[Tensor] = [torch.empty(0, dtype=torch.int64)] * volume
            out_idx: list[Tensor] = [torch.empty(0, dtype=torch.int64)] * volume
            keys_by_row = level.keys if level.order is None else pack_keys(level.coords)
            for k in range(centre):
                nbr = level.lookup(keys_by_row + deltas[k])
                out_rows = torch.nonzero(nbr >= 0).squeeze(1)
                in_rows = nbr[out_rows]
                in_idx[k], out_idx[k] = in_rows, out_rows
                in_idx[volume - 1 - k], out_idx[volume - 1 - k] = out_rows, in_rows
            n = level.coords.shape[0]
            self._maps[key] = KernelMap(tuple(in_idx), tuple(out_idx), n, n, identity=centre)
        return self._maps[key]

    def downsample(self, stride: int) -> KernelMap:
        """Map of the kernel-2 stride-2 convolution from stride ``stride`` to ``2 * stride``.

        Registers the coarse coordinates (each occupied parent cell once, key-sorted). Offset
        ``k = 4 dx + 2 dy + dz`` for the child position (dx, dy, dz) in {0, 1}^3 of the parent cell.
        """
        key = ("down", stride)
        if key not in self._maps:
            level = self._levels[stride]
            coarse = 2 * stride
            fine = level.coords
            parent = torch.cat([fine[:, :1], torch.div(fine[:, 1:], coarse, rounding_mode="floor") * coarse], 1)
            child = torch.div(fine[:, 1:] - parent[:, 1:], stride, rounding_mode="floor")
            offset = child[:, 0] * 4 + child[:, 1] * 2 + child[:, 2]
            coarse_keys, inverse = torch.unique(pack_keys(parent), return_inverse=True)
            self.register(unpack_keys(coarse_keys), coarse)
            order = torch.argsort(offset, stable=True)
            counts = torch.bincount(offset, minlength=8).tolist()
            in_idx = torch.split(order, counts)
            out_idx = tuple(inverse[rows] for rows in in_idx)
            self._maps[key] = KernelMap(in_idx, out_idx, fine.shape[0], coarse_keys.shape[0])
        return self._maps[key]

    def upsample(self, stride: int) -> KernelMap:
        """Map of the kernel-2 stride-2 transposed convolution from ``stride`` back to ``stride // 2``.

        Needs the finer level to have been down-sampled through this cache (its coordinates are
        restored exactly); raises KeyError otherwise.
        """
        if stride % 2 or ("down", stride // 2) not in self._maps:
            raise KeyError(
                f"no stride-{stride // 2} level was down-sampled to stride {stride} in this cache: "
                "a transposed convolution restores the coordinates of an earlier down-sampling"
            )
        return self._maps[("down", stride // 2)].transposed()


class SparseTensor:
    """Features on occupied voxels: coords ``[M, 4]`` int64 (batch, x, y, z), feats ``[M, C]`` float.

    ``stride`` is the tensor stride in finest-voxel units (coordinates are multiples of it);
    ``cache`` holds the kernel maps shared by every tensor derived from the same input.
    """

    def __init__(self, coords: Tensor, feats: Tensor, stride: int = 1, cache: KernelMapCache | None = None) -> None:
        if feats.dim() != 2:
            raise ValueError(f"feats must have shape [M, C], got {list(feats.shape)}")
        if coords.dim() != 2 or coords.shape[1] != 4:
            raise ValueError(f"coords must have shape [M, 4] (batch, x, y, z), got {list(coords.shape)}")
        if coords.shape[0] != feats.shape[0]:
            raise ValueError(f"coords has {coords.shape[0]} rows but feats has {feats.shape[0]}")
        if coords.dtype != torch.int64:
            if coords.dtype.is_floating_point or coords.dtype == torch.bool:
                raise ValueError(f"coords must be an integer tensor, got {coords.dtype}")
            coords = coords.to(torch.int64)
        self.coords = coords
        self.feats = feats
        self.stride = stride
        self.cache = cache if cache is not None else KernelMapCache()
        self.cache.register(coords, stride)

    def with_feats(self, feats: Tensor) -> SparseTensor:
        """A tensor on the same coordinates (and cache) with other features ``[M, C']``."""
        return SparseTensor(self.coords, feats, self.stride, self.cache)

    def __len__(self) -> int:
        return self.coords.shape[0]

    def __repr__(self) -> str:
        return f"SparseTensor(voxels={len(self)}, channels={self.feats.shape[1]}, stride={self.stride})"
