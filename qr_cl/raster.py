"""Projection, tile binning and depth sort: Gaussians + camera -> RasterPlan (geometry only).

Pipeline: ``project.cl`` (one work-item per Gaussian) -> exclusive scan of tiles touched ->
``emit_keys`` (one key per Gaussian and touched tile: ``tile << 32 | depth bits``) -> sort ->
``tile_ranges``. A RasterPlan never depends on features, so it can serve every channel count.
"""
from __future__ import annotations

from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.algorithm import RadixSort
from pyopencl.scan import ExclusiveScanKernel

from .device import Runtime, runtime

TILE = 16


@dataclass
class RasterPlan:
    """Everything the per-pixel kernels need, on the device.

    splats [N,8] float32 (mean2d x, y in px; conic a, b, c; opacity; depth; 0), radii [N] int32
    (0 = culled), ranges [tiles, 2] int32 [start, end) into ids, ids [max(M,1)] int32 depth-sorted
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
        return (self.width + TILE - 1) // TILE

    @property
    def tiles_y(self) -> int:
        return (self.height + TILE - 1) // TILE

    def meta(self) -> dict[str, np.ndarray]:
        """Host copies: means2d [N,2] px, conics [N,3], depths [N], radii [N] int32, opacities [N],
        tile_ranges [tiles,2] [start, end) into flatten_ids [M] (depth-sorted Gaussian ids per
        tile, as gsplat names them), n_keys = M."""
        s = self.splats.get().reshape(-1, 8)
        return {"means2d": s[:, 0:2].copy(), "conics": s[:, 2:5].copy(), "opacities": s[:, 5].copy(),
                "depths": s[:, 6].copy(), "radii": self.radii.get(),
                "tile_ranges": self.ranges.get().reshape(-1, 2),
                "flatten_ids": self.ids.get()[:self.n_keys], "n_keys": self.n_keys}


@lru_cache(maxsize=None)
def exclusive_scan(context: cl.Context) -> ExclusiveScanKernel:
    """pyopencl's exclusive int32 prefix sum for ``context`` (built once per context)."""
    return ExclusiveScanKernel(context, np.int32, "a+b", "0")


@lru_cache(maxsize=None)
def _radix_sort(context: cl.Context) -> RadixSort:
    return RadixSort(context, "ulong *keys, int *values", key_expr="keys[i]",
                     sort_arg_names=["keys", "values"], key_dtype=np.uint64)


def to_device(rt: Runtime, array: np.ndarray, dtype=np.float32) -> cla.Array:
    """A contiguous device copy of a host array."""
    return cla.to_device(rt.queue, np.ascontiguousarray(array, dtype=dtype))


@contextmanager
def host_output(rt: Runtime, array: np.ndarray):
    """A device buffer that the kernels write straight into ``array`` (C-contiguous host memory).

    Zero-copy on CPU devices (USE_HOST_PTR); on leaving the block the buffer is mapped for
    reading, which on discrete GPUs copies the result into ``array``. Avoids allocating and
    copying a second [H*W, C] image.
    """
    buf = cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=array)
    yield buf
    mapped, _ = cl.enqueue_map_buffer(rt.queue, buf, cl.map_flags.READ, 0, array.shape, array.dtype)
    mapped.base.release(rt.queue)
    rt.queue.finish()


def sort_pairs(rt: Runtime, keys: cla.Array, values: cla.Array, key_bits: int) -> tuple[cla.Array, cla.Array]:
    """Sort (key, value) pairs by the low ``key_bits`` bits of the uint64 keys.

    On a CPU device the host is the device: numpy's stable argsort on the mapped data is much
    faster than pyopencl's GPU-style RadixSort there (see bench/test_bench_binning.py). On other
    devices pyopencl's RadixSort runs on the device.
    """
    if rt.is_cpu:
        host_keys = keys.get()
        order = np.argsort(host_keys, kind="stable")
        return (cla.to_device(rt.queue, host_keys[order]), cla.to_device(rt.queue, values.get()[order]))
    (sorted_keys, sorted_values), _ = _radix_sort(rt.context)(keys, values, key_bits=key_bits)
    return sorted_keys, sorted_values


def project(rt: Runtime, means: cla.Array, quats: cla.Array, scales: cla.Array, opacities: cla.Array,
            viewmat: np.ndarray, K: np.ndarray, width: int, height: int, near: float, far: float):
    """Run project.cl: returns (splats [N,8], radii [N], rects [N,4], tiles_touched [N])."""
    n = means.shape[0]
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    splats = cla.empty(rt.queue, (n, 8), np.float32)
    radii = cla.empty(rt.queue, n, np.int32)
    rects = cla.empty(rt.queue, (n, 4), np.int32)
    touched = cla.empty(rt.queue, n, np.int32)
    view = to_device(rt, np.asarray(viewmat, np.float32).reshape(16))
    rt.kernel("project.cl", "project")(
        rt.queue, (n,), None, np.int32(n), means.data, quats.data, scales.data, opacities.data,
        view.data, np.float32(K[0, 0]), np.float32(K[1, 1]), np.float32(K[0, 2]), np.float32(K[1, 2]),
        np.int32(width), np.int32(height), np.float32(near), np.float32(far),
        np.int32(tiles_x), np.int32(tiles_y), splats.data, radii.data, rects.data, touched.data)
    return splats, radii, rects, touched


def bin_and_sort(rt: Runtime, splats: cla.Array, rects: cla.Array, touched: cla.Array,
                 width: int, height: int) -> tuple[cla.Array, cla.Array, int]:
    """Keys per (Gaussian, tile), sorted by tile then depth.

    Returns (ranges [tiles,2], ids [max(M,1)], M) for M keys.
    """
    n = touched.size
    tiles_x, tiles_y = (width + TILE - 1) // TILE, (height + TILE - 1) // TILE
    n_tiles = tiles_x * tiles_y
    ranges = cla.zeros(rt.queue, (n_tiles, 2), np.int32)
    offsets = cla.empty_like(touched)
    exclusive_scan(rt.context)(touched, offsets)
    last = np.empty(2, np.int32)
    cl.enqueue_copy(rt.queue, last[:1], offsets.base_data, src_offset=offsets.offset + 4 * (n - 1))
    cl.enqueue_copy(rt.queue, last[1:], touched.base_data, src_offset=touched.offset + 4 * (n - 1))
    m = int(last[0]) + int(last[1])
    if m == 0:
        return ranges, cla.zeros(rt.queue, 1, np.int32), 0
    keys = cla.empty(rt.queue, m, np.uint64)
    values = cla.empty(rt.queue, m, np.int32)
    rt.kernel("binning.cl", "emit_keys")(rt.queue, (n,), None, np.int32(n), rects.data, offsets.data,
                                         splats.data, np.int32(tiles_x), keys.data, values.data)
    key_bits = 32 + max(1, int(n_tiles - 1).bit_length())
    keys, ids = sort_pairs(rt, keys, values, key_bits)
    rt.kernel("binning.cl", "tile_ranges")(rt.queue, (m,), None, np.int32(m), keys.data, ranges.data)
    return ranges, ids, m


def rasterize_plan(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, opacities: np.ndarray,
                   viewmat: np.ndarray, K: np.ndarray, width: int, height: int,
                   near: float = 0.01, far: float = 1e10, rt: Runtime | None = None) -> RasterPlan:
    """Project, bin and sort Gaussians for one camera.

    means [N,3], quats [N,4] unit w,x,y,z, scales [N,3] activated, opacities [N] activated (float32
    host arrays); viewmat [4,4] world-to-camera; K [3,3] intrinsics in px; width/height in px.
    """
    rt = rt or runtime()
    dev = [to_device(rt, a) for a in (means, quats, scales, opacities)]
    splats, radii, rects, touched = project(rt, *dev, viewmat, np.asarray(K), width, height, near, far)
    ranges, ids, n_keys = bin_and_sort(rt, splats, rects, touched, width, height)
    return RasterPlan(rt, int(width), int(height), splats, radii, ranges, ids, n_keys)
