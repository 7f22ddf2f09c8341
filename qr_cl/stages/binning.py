"""Binning and depth sort (binning.cl): splats -> per-tile depth-sorted Gaussian lists.

Exclusive scan of the tiles each Gaussian touches -> ``emit_keys`` (one key per Gaussian and
touched tile: ``tile << 32 | depth bits``) -> sort -> ``tile_ranges``. The result, with the
splats it indexes, is a :class:`RasterPlan`: geometry only, never features, so one plan serves
every channel count and sampler. Twin: :mod:`qr_cl.stages.binning_ref`.
"""
from __future__ import annotations

import threading
import warnings
from dataclasses import dataclass
from functools import cached_property, lru_cache

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
import torch
from pyopencl.algorithm import RadixSort

from ..runtime import (FOOTPRINT_INTS, SPLAT, SPLAT_FLOATS, Runtime, check_buffer, device_empty, device_zeros, exclusive_scan,
                       host_empty, last_value, to_device)
from .project import Projection, tile_grid

BIN_CHUNKS_PER_CORE = 4   # the CPU binning's work-items per compute unit
PLAN_META_KEYS = ("means2d", "conics", "opacities", "depths", "radii", "tile_ranges", "flatten_ids",
                  "n_keys")   # the entries of RasterPlan.meta


@dataclass(frozen=True, kw_only=True)
class RasterPlan:
    """Everything the per-pixel kernels need, on the device (built by keyword, never changed).

    splats [N,8] float32 (mean2d in px, conic, opacity, depth and sigma_max = ln(opacity /
    ALPHA_MIN), the exponent beyond which its alpha is skipped, in the slots of
    :data:`~qr_cl.runtime.SPLAT`), radii [N,2] int32
    (x, y half-sides in px of the box it is binned within; 0 = culled), ranges [tiles, 2] int32 [start, end) into ids, ids [max(M,1)] int32 depth-sorted
    Gaussian ids per tile (M = n_keys; one unused entry when M = 0), width/height in px.
    Needs N >= 1 (callers handle empty scenes).
    """

    runtime: Runtime
    width: int
    height: int
    splats: cla.Array
    radii: cla.Array
    ranges: cla.Array
    ids: cla.Array
    n_keys: int

    @property
    def tiles_x(self) -> int:
        return tile_grid(self.width, self.height)[0]

    @property
    def tiles_y(self) -> int:
        return tile_grid(self.width, self.height)[1]

    @property
    def n_gaussians(self) -> int:
        return self.splats.shape[0]

    @property
    def nbytes(self) -> int:
        """Device bytes held by the plan."""
        return self.splats.nbytes + self.radii.nbytes + self.ranges.nbytes + self.ids.nbytes

    @cached_property
    def longest_list(self) -> int:
        """The longest tile list (Gaussians), read from the device once: how far a walk goes."""
        ranges = self.ranges.get().reshape(-1, 2)
        return int((ranges[:, 1] - ranges[:, 0]).max(initial=0))

    def ray_args(self) -> dict:
        """The tile-list arguments every per-ray kernel declares (RAY_ARGS in kernels/select.cl)."""
        return {"ranges": self.ranges, "ids": self.ids, "splats": self.splats, "width": self.width,
                "height": self.height, "tiles_x": self.tiles_x}

    def meta(self) -> dict[str, np.ndarray]:
        """Host copies: means2d [N,2] px, conics [N,3], depths [N], radii [N,2] int32 (x, y px; 0 =
        culled), opacities [N], tile_ranges [tiles,2] [start, end) into flatten_ids [M]
        (depth-sorted Gaussian ids per tile), n_keys = M. Large arrays come from the host pool."""
        s = _get(self.splats).reshape(-1, SPLAT_FLOATS)

        def column(cols):
            out = host_empty((len(s), cols.stop - cols.start) if isinstance(cols, slice) else len(s))
            out[...] = s[:, cols]
            return out
        return {"means2d": column(SPLAT.mean), "conics": column(SPLAT.conic), "opacities": column(SPLAT.opacity),
                "depths": column(SPLAT.depth), "radii": _get(self.radii),
                "tile_ranges": _get(self.ranges).reshape(-1, 2),
                "flatten_ids": _get(self.ids)[:self.n_keys], "n_keys": self.n_keys}


def _get(array: cla.Array) -> np.ndarray:
    """A host copy of a device array, in a pooled host array (no fresh pages for large ones)."""
    return array.get(ary=host_empty(array.shape, array.dtype))


#: Bytes of the largest buffer pyopencl's radix sort makes per key: its scan's 2^2 int32 bucket
#: counts per key (2 bits a pass).
SORT_BYTES_PER_KEY = 16


@lru_cache(maxsize=None)
def radix_sorter(context: cl.Context) -> RadixSort:
    """pyopencl's RadixSort of (uint64 key, int32 value) pairs for ``context`` (built once)."""
    return RadixSort(context, "ulong *keys, int *values", key_expr="keys[i]",
                     sort_arg_names=["keys", "values"], key_dtype=np.uint64)


@lru_cache(maxsize=None)
def device_sort_works(context: cl.Context) -> bool:
    """Whether pyopencl's RadixSort sorts 100k random (key, value) pairs on this context's device
    as numpy's stable argsort does (checked once; its scans share pyopencl's scan race, see
    :func:`qr_cl.runtime.memory.device_scan_works`)."""
    queue = cl.CommandQueue(context)
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 1 << 40, 100_000).astype(np.uint64)
    values = np.arange(len(keys), dtype=np.int32)
    (k, v), _ = radix_sorter(context)(cla.to_device(queue, keys), cla.to_device(queue, values), key_bits=40)
    order = np.argsort(keys, kind="stable")
    ok = np.array_equal(k.get(), keys[order]) and np.array_equal(v.get(), values[order])
    if not ok:
        warnings.warn("pyopencl's RadixSort sorted wrongly on this device; qr-cl sorts on the host")
    return ok


_SORT_THREADS = threading.Lock()


def host_sort(keys: torch.Tensor, out: tuple[torch.Tensor, torch.Tensor] | None = None
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """(sorted keys, int64 order) of a 1-D tensor by torch's stable sort, run on the calling
    thread alone. torch's OpenMP team gains little on N <= millions of keys, and its threads then
    spin-wait for more work (libgomp's default) while the next kernels want every core, which
    measured slower, the selection kernel right after the sort most of all. The thread count is
    torch's global setting, so it is swapped under a lock and always restored."""
    with _SORT_THREADS:
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return torch.sort(keys, stable=True, out=out)
        finally:
            torch.set_num_threads(threads)


def sort_pairs(rt: Runtime, keys: cla.Array, values: cla.Array, key_bits: int) -> tuple[cla.Array, cla.Array]:
    """Sort (key, value) pairs by the low ``key_bits`` bits of the uint64 keys.

    On a CPU-shaped runtime the host is the device: the pairs are sorted on the host by torch's
    stable sort (:func:`host_sort`; a radix sort for int64 keys; keys of at most 63 bits keep
    their order as int64), measured faster than numpy's stable argsort (a merge sort) and than
    pyopencl's GPU-style RadixSort there (see bench/test_bench_binning.py); its outputs are pooled
    host arrays. On GPU-shaped ones (:attr:`qr_cl.runtime.Runtime.gpu_shaped`) pyopencl's RadixSort
    runs on the device, once :func:`device_sort_works` has checked it there, unless the device has a
    loop limit (its scans loop over intervals that grow with the keys); all are stable, so the
    order is the same.
    """
    if not rt.gpu_shaped or rt.loop_limit is not None or not device_sort_works(rt.context):
        host_keys = _get(keys)
        if key_bits > 63:
            raise ValueError(f"sort keys of {key_bits} bits: at most 63 are supported")
        sorted_keys, order = host_empty(keys.shape, np.uint64), host_empty(keys.shape, np.int64)
        host_sort(torch.from_numpy(host_keys.view(np.int64)),
                  out=(torch.from_numpy(sorted_keys.view(np.int64)), torch.from_numpy(order)))
        host_values = _get(values)
        return to_device(rt, sorted_keys, np.uint64), to_device(
            rt, np.take(host_values, order, out=host_empty(values.shape, values.dtype)), np.int32)
    check_buffer(rt, SORT_BYTES_PER_KEY * keys.size, f"the device sort of {keys.size} keys")
    (sorted_keys, sorted_values), _ = radix_sorter(rt.context)(keys, values, key_bits=key_bits,
                                                               allocator=rt.pool)
    return sorted_keys, sorted_values


def bin_and_sort(rt: Runtime, proj: Projection, width: int, height: int) -> tuple[cla.Array, cla.Array, int]:
    """Keys per (Gaussian, tile), sorted by tile then depth, from :func:`qr_cl.stages.project.project`.

    Returns (ranges [tiles,2], ids [max(M,1)], M) for M keys. GPU-shaped runtimes sort the M keys
    (:func:`sort_pairs`), and so do devices with a loop limit (the counting sort's few work-items
    each walk many Gaussians); CPU-shaped ones sort the N Gaussians by depth and then the pairs by
    tile (:func:`_bin_counted`): the same ids.
    """
    tiles_x, tiles_y = tile_grid(width, height)
    n_tiles = tiles_x * tiles_y
    if not rt.gpu_shaped and rt.loop_limit is None:
        return _bin_counted(rt, proj, tiles_x, n_tiles)
    n, touched = proj.tiles_touched.size, proj.tiles_touched
    ranges = device_zeros(rt, (n_tiles, 2), np.int32)
    offsets = exclusive_scan(rt, touched, device_empty(rt, touched.shape, touched.dtype))
    m = last_value(offsets) + last_value(touched)
    if m == 0:
        return ranges, device_zeros(rt, 1, np.int32), 0
    keys = device_empty(rt, m, np.uint64)
    values = device_empty(rt, m, np.int32)
    rt.launch("emit_keys", n, n=n, footprints=proj.footprints, offsets=offsets, splats=proj.splats,
              tiles_x=tiles_x, keys=keys, values=values)
    key_bits = 32 + max(1, int(n_tiles - 1).bit_length())
    keys, ids = sort_pairs(rt, keys, values, key_bits)
    rt.launch("tile_ranges", m, m=m, keys=keys, ranges=ranges)
    return ranges, ids, m


def _bin_counted(rt: Runtime, proj: Projection, tiles_x: int, n_tiles: int) -> tuple[cla.Array, cla.Array, int]:
    """CPU-shaped binning: the Gaussians sorted by depth key on the host (:func:`host_sort` of N
    keys instead of M pairs; the culled ones, keyed INT32_MAX, come last and are cut off), then
    their M (Gaussian, tile) pairs by a stable counting sort by tile (bin_count / bin_fill). Each
    tile's list is by depth, then index, as the key sort gives it. No scan of the tiles touched:
    M is the histogram's total. Sorting N keys rather than M pairs measured faster on CPUs
    (the "binning+sort" rows of qr-cl bench)."""
    keys = torch.from_numpy(_get(proj.depth_keys))
    sorted_keys, by_depth = host_sort(keys)
    n = int(torch.searchsorted(sorted_keys, np.iinfo(np.int32).max))
    if n == 0:
        return device_zeros(rt, (n_tiles, 2), np.int32), device_zeros(rt, 1, np.int32), 0
    order = to_device(rt, by_depth[:n].numpy(), np.int32)
    chunks = max(1, min(n, BIN_CHUNKS_PER_CORE * rt.device.max_compute_units))
    sorted_footprints = device_empty(rt, (n, FOOTPRINT_INTS), np.int32)
    rt.launch("gather_footprints", n, n=n, order=order, footprints=proj.footprints, sorted=sorted_footprints)
    args = dict(n=n, per=-(-n // chunks), n_chunks=chunks, order=order, sorted=sorted_footprints,
                splats=proj.splats, tiles_x=tiles_x)
    hist = device_zeros(rt, n_tiles * chunks, np.int32)
    rt.launch("bin_count", chunks, local_size=(1,), **args, n_tiles=n_tiles, hist=hist)
    counts = hist.get()
    ends = np.cumsum(counts, dtype=np.int64)
    m = int(ends[-1])
    ids = device_empty(rt, m, np.int32)            # m >= n: each Gaussian kept touches a tile
    rt.launch("bin_fill", chunks, local_size=(1,), **args, cursor=to_device(rt, ends - counts, np.int32), ids=ids)
    tile_ends = ends[chunks - 1::chunks]
    tile_starts = tile_ends - counts.reshape(n_tiles, chunks).sum(1)
    ranges = np.where((tile_ends > tile_starts)[:, None], np.stack([tile_starts, tile_ends], 1), 0)
    return to_device(rt, ranges, np.int32), ids, m
