"""Transpose stage (transpose.cl): a Selection's entries grouped by Gaussian, the blend backward's
view of the selection (:mod:`qr_cl.stages.blend`), and the order in which that backward takes
the Gaussians. No float atomics: the same bytes on every launch shape.

CPU-shaped runtimes run a counting sort by a few long work-items (:func:`counted_transpose`),
GPU-shaped ones a device sort of (Gaussian, entry) keys (:func:`sorted_transpose`). Within a
Gaussian, entries are ordered by ray, then by position in the ray.
"""
from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.scan import InclusiveScanKernel

from ..runtime import TILE, device_empty, device_scan_works, device_zeros, exclusive_scan, last_value, to_device
from .binning import sort_pairs
from .select import Selection

CHUNKS_PER_CORE = 4          # the CPU transpose splits the rays into this many chunks per compute unit
MAX_HIST = 1 << 24            # ... and n_gaussians * chunks stays below this many ints


class Transpose(NamedTuple):
    """A Selection's entries grouped by Gaussian, what :func:`transpose` returns for its caller to
    keep: cursor [N * chunks] int32 (cursor[(g+1) * chunks - 1] is the end of Gaussian g's
    segment), per transposed entry its ray [E] int32, weight [E] float32 and index [E] int32 into
    the selection's ids, and the order [N] int32 in which the blend backward takes the Gaussians
    (:func:`backward_order`)."""

    cursor: cla.Array
    ray: cla.Array
    weight: cla.Array
    entry: cla.Array
    chunks: int
    order: cla.Array

    @property
    def nbytes(self) -> int:
        """Device bytes held."""
        return sum(a.nbytes for a in (self.cursor, self.ray, self.weight, self.entry, self.order))


def transpose(sel: Selection) -> Transpose:
    """The entries of ``sel`` grouped by Gaussian, made anew on every call (the caller keeps
    them): :func:`sorted_transpose` on GPU-shaped runtimes and on devices with a loop limit (the
    counting sort's few work-items each walk many rays), :func:`counted_transpose` on CPU-shaped
    ones; the same bytes either way."""
    rt = sel.plan.runtime
    return (sorted_transpose if rt.gpu_shaped or rt.loop_limit is not None else counted_transpose)(sel)


def longest_segment(t: Transpose) -> int:
    """The most transposed entries of one Gaussian (read from the device): how far a walk over a
    Gaussian's entries goes."""
    ends = t.cursor.get().reshape(-1, t.chunks)[:, -1].astype(np.int64)
    return int(np.diff(ends, prepend=0).max(initial=0))


def backward_order(sel: Selection, t: Transpose, g0: int = 0, g1: int | None = None) -> cla.Array:
    """The Gaussians g0..g1 (default all N) int32 in the order the blend backward takes them: by
    the tile, then the ray, of the first ray of their transposed entries (Gaussians without entries
    last), so that neighbouring work-items gather neighbouring rows of dImage. Made with the
    transpose ``t`` of ``sel``, by host work only (a training step's next transpose runs on another
    thread); a row part's (g0..g1 not all N) is picked from it on the host."""
    if g0 == 0 and g1 in (None, sel.n_gaussians):
        return t.order
    order = t.order.get()
    return to_device(sel.plan.runtime, order[(order >= g0) & (order < g1)], np.int32)


def counted_transpose(sel: Selection) -> Transpose:
    """CPU-shaped transpose (transpose_count / transpose_fill): a stable counting sort by a few
    long work-items, each owning a contiguous chunk of rays."""
    rt = sel.plan.runtime
    n, n_rays = sel.n_gaussians, sel.n_rays
    # enough chunks to keep every core busy, no more: each adds a cursor slot per Gaussian, and a
    # few chunks per core take about the time of many with a fraction of the cursor memory
    chunks = max(1, min(CHUNKS_PER_CORE * rt.device.max_compute_units, n_rays, MAX_HIST // max(n, 1)))
    rays_per = -(-n_rays // chunks) if n_rays else 1
    cursor = device_zeros(rt, n * chunks, np.int32)
    args = dict(n_rays=n_rays, rays_per=rays_per, n_chunks=chunks, offsets=sel.offsets,
                count=sel.count, n_entries=sel.ids.size, n=n, sel_ids=sel.ids)
    if n_rays:
        rt.launch("transpose_count", chunks, **args, bin_shift=0, hist=cursor)
    total = int(cla.sum(cursor).get())      # the entries placed (counts bounded, ids in the scene)
    t_ray = device_empty(rt, max(total, 1), np.int32)
    t_w = device_empty(rt, max(total, 1), np.float32)
    t_entry = device_empty(rt, max(total, 1), np.int32)
    if n_rays:
        exclusive_scan(rt, cursor)
        rt.launch("transpose_fill", chunks, **args, sel_w=sel.weights, cursor=cursor,
                  t_ray=t_ray, t_w=t_w, t_entry=t_entry)
    return Transpose(cursor, t_ray, t_w, t_entry, chunks, _first_ray_order(sel, cursor, t_ray, chunks))


def _first_ray_order(sel: Selection, cursor: cla.Array, t_ray: cla.Array, chunks: int) -> cla.Array:
    """The order [N] of :func:`backward_order`, from a transpose's cursor and rays."""
    plan = sel.plan
    ends = cursor.get().reshape(-1, chunks)[:, -1].astype(np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    first = t_ray.get()[np.minimum(starts, t_ray.size - 1)]
    xy = (np.stack([first % plan.width, first // plan.width], 1) if sel.pixels is None
          else sel.pixels[np.minimum(first, max(len(sel.pixels) - 1, 0))])
    tile = np.where(ends > starts, (xy[:, 1] // TILE) * plan.tiles_x + xy[:, 0] // TILE, np.iinfo(np.int32).max)
    return to_device(plan.runtime, np.lexsort((first, tile)), np.int32)


@lru_cache(maxsize=None)
def _max_scan(context: cl.Context) -> InclusiveScanKernel:
    return InclusiveScanKernel(context, np.int32, "max(a, b)", "0")


def sorted_transpose(sel: Selection) -> Transpose:
    """GPU-shaped transpose (transpose_keys -> device sort -> transpose_gather -> max-scan): one
    work-item per ray or entry; the same entries in the same order as :func:`counted_transpose`,
    with one chunk (cursor[g] = the end of Gaussian g's segment)."""
    rt, n, n_rays = sel.plan.runtime, sel.n_gaussians, sel.n_rays
    spans = device_zeros(rt, max(n_rays, 1), np.int32)       # the counts bounded by the buffers
    if n_rays:
        rt.launch("ray_spans", n_rays, n_rays=n_rays, offsets=sel.offsets, count=sel.count,
                  n_entries=sel.ids.size, spans=spans)
    compact = exclusive_scan(rt, spans, device_empty(rt, max(n_rays, 1), np.int32))
    total = last_value(compact) + last_value(spans) if n_rays else 0
    cursor = device_zeros(rt, n, np.int32)
    t_ray, t_w = device_empty(rt, max(total, 1), np.int32), device_empty(rt, max(total, 1), np.float32)
    t_entry = device_empty(rt, max(total, 1), np.int32)
    if total:
        keys, values = device_empty(rt, total, np.uint64), device_empty(rt, total, np.int32)
        entry_ray, entry_w = device_empty(rt, total, np.int32), device_empty(rt, total, np.float32)
        entry_index = device_empty(rt, total, np.int32)
        rt.launch("transpose_keys", n_rays, n_rays=n_rays, offsets=sel.offsets, count=sel.count,
                  n_entries=sel.ids.size, n=n, compact=compact, sel_ids=sel.ids, sel_w=sel.weights, keys=keys, values=values,
                  entry_ray=entry_ray, entry_w=entry_w, entry_index=entry_index)
        keys, values = sort_pairs(rt, keys, values, 32 + max(1, int(n).bit_length()))
        rt.launch("transpose_gather", total, n=total, n_gaussians=n, keys=keys, values=values, entry_ray=entry_ray,
                  entry_w=entry_w, entry_index=entry_index, t_ray=t_ray, t_w=t_w, t_entry=t_entry,
                  ends=cursor)
        if rt.loop_limit is None and device_scan_works(rt.context):
            _max_scan(rt.context)(cursor)
        else:
            cursor.set(np.maximum.accumulate(cursor.get()))
    return Transpose(cursor, t_ray, t_w, t_entry, 1, _first_ray_order(sel, cursor, t_ray, 1))
