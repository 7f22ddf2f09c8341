"""Selection stage (select.cl, transpose.cl): which Gaussians each ray blends, with what weight.

A Selection depends only on geometry, camera, sampler and K, never on features: it is computed
once per view and shared by the blend forward and backward (:mod:`qr_cl.stages.blend`).
Twin: :mod:`qr_cl.stages.select_ref`.

Samplers:
    ``volume``   every Gaussian V-Render blends (alpha >= 1/255, until T would drop to <= 1e-4),
                 w_i = T_i alpha'_i; background weight = the final T.
    ``quantile`` Algorithm 1 of the paper (K quantile Gaussians), w = T^Q alpha' / (1 - T^Q).
    ``topk``     the K largest V-Render weights, re-composited in depth order among the selected,
                 normalized by 1 / (1 - T) as Q-Render.
    ``stratified`` Stratified-K (App. E): Algorithm 1 with the K boundaries at quantiles of the
                 normal fitted to the ray's transmittance values (a first V-Render walk).
For quantile, topk and stratified the normalized weights sum to 1, so the background only shows through rays
that selected nothing (background weight 1 there, 0 elsewhere).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Callable, NamedTuple

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.scan import InclusiveScanKernel

from ..runtime import (BLOCK_GROUP, SAMPLERS, TILE, Runtime, check_buffer, device_empty, device_zeros, exclusive_scan,
                       last_value, to_device)
from .binning import SORT_BYTES_PER_KEY, RasterPlan, sort_pairs

CHUNKS_PER_CORE = 4          # the CPU transpose splits the rays into this many chunks per compute unit
MAX_HIST = 1 << 24            # ... and n_gaussians * chunks stays below this many ints


class Transpose(NamedTuple):
    """A Selection's entries grouped by Gaussian (:meth:`Selection.transpose`): cursor [N * chunks]
    int32 (cursor[(g+1) * chunks - 1] is the end of Gaussian g's segment), and per transposed
    entry its ray [E] int32, weight [E] float32 and index [E] int32 into the selection's ids."""

    cursor: cla.Array
    ray: cla.Array
    weight: cla.Array
    entry: cla.Array
    chunks: int


@dataclass
class Selection:
    """Per-ray (Gaussian id, weight) lists on the device.

    Rays: the whole image (``pixels is None``, ray p = y * width + x) or a pixel subset
    (``pixels`` [P,2] int32 (x, y), ray p = row p). Entries of ray p are
    ``[offsets[p], offsets[p] + count[p])`` of ``ids`` / ``weights`` (int32 / float32; quantile
    and topk: dense rows of K at p * K, padded with -1 / 0). Per ray (float32 [P]): ``t_walk`` the
    transmittance where the ray's walk stopped, ``t_sel`` the transmittance among the selected
    Gaussians before normalization (T^Q; the final T for volume), ``t_rem`` the background weight.
    ``k`` is K (0 for volume); ``n_gaussians`` is N of the plan. ``transposed`` caches
    :meth:`transpose` (the blend backward's view of the selection); ``owners`` the backward
    scatter's owner bounds by number of owners (:func:`qr_cl.stages.blend.owner_bounds`).
    ``pending`` is the deferred selection kernel of ``select(..., defer=True)`` until it is
    enqueued: by the first blend forward, fused with it, or by :meth:`ready`.
    """

    plan: RasterPlan
    sampler: str
    k: int
    pixels: np.ndarray | None
    ids: cla.Array
    weights: cla.Array
    offsets: cla.Array
    count: cla.Array
    t_walk: cla.Array
    t_sel: cla.Array
    t_rem: cla.Array
    transposed: Transpose | None = field(default=None, repr=False)
    order: cla.Array | None = field(default=None, repr=False)
    owners: dict[int, cla.Array] = field(default_factory=dict, repr=False)
    pending: Callable[..., None] | None = field(default=None, repr=False)

    def ready(self) -> Selection:
        """Enqueue the deferred selection kernel, if it still is (see ``pending``); returns self.
        Kernels and reads enqueued after this see the selection (the queue is in order)."""
        if self.pending is not None:
            launch, self.pending = self.pending, None
            launch()
        return self

    @property
    def n_rays(self) -> int:
        return self.plan.width * self.plan.height if self.pixels is None else len(self.pixels)

    @property
    def n_gaussians(self) -> int:
        return self.plan.n_gaussians

    @property
    def nbytes(self) -> int:
        """Device bytes held by the selection (and its cached transpose and owner bounds)."""
        arrays = [self.ids, self.weights, self.offsets, self.count, self.t_walk, self.t_sel, self.t_rem]
        arrays += [a for a in (*(self.transposed or ()), self.order) if isinstance(a, cla.Array)]
        arrays += list(self.owners.values())
        return sum(a.nbytes for a in arrays)

    def launch(self) -> tuple[int, int]:
        """(global size of a per-ray kernel, full-image flag)."""
        return ray_launch(self.plan, self.pixels)

    def transpose(self) -> Transpose:
        """The entries grouped by Gaussian (transpose.cl, no float atomics), computed once and kept
        in ``transposed`` (and :meth:`backward_order` in ``order``): a counting sort by a few long
        work-items on CPU-shaped runtimes, a device sort of (Gaussian, entry) keys on GPU-shaped
        ones; the same bytes either way.

        Within a Gaussian, entries are ordered by ray then by position in the ray.
        """
        if self.transposed is None:
            self.transposed = (_transpose_sorted if self.plan.runtime.gpu_shaped else _transpose_counted)(self)
            self.order = _backward_order(self, self.transposed)
        return self.transposed

    def backward_order(self) -> cla.Array:
        """The Gaussians [N] int32 in the order the blend backward takes them: by the tile, then
        the ray, of the first ray of their transposed entries (Gaussians without entries last),
        so neighbouring work-items gather neighbouring rows of dImage. Made with the transpose,
        by host work only (a training step's next transpose runs on another thread)."""
        self.transpose()
        return self.order

    def spans(self) -> tuple[np.ndarray, np.ndarray]:
        """(offsets, count) [P] int64 on the host, each ray's count bounded by the id buffer as
        the kernels bound it (``ray_span`` in kernels/common.h)."""
        n, size = self.n_rays, self.ids.size
        offsets = np.clip(self.offsets.get()[:n].astype(np.int64), 0, size)
        return offsets, np.clip(self.count.get()[:n].astype(np.int64), 0, size - offsets)

    def host(self) -> dict[str, np.ndarray]:
        """Host copies as dense arrays: ids [P,L] (-1 padded) and weights [P,L] (0 padded) with L the
        longest list, count, t_walk, t_sel, t_rem [P]."""
        n = self.n_rays
        offsets, count = self.spans()
        count = count.astype(np.int32)
        width = int(count.max(initial=0))
        cols = np.arange(width)
        valid = cols[None] < count[:, None]
        index = np.where(valid, offsets[:, None] + cols[None], 0)
        ids_all, w_all = self.ids.get(), self.weights.get()
        ids = np.where(valid, ids_all[index] if ids_all.size else 0, -1).astype(np.int32)
        w = np.where(valid, w_all[index] if w_all.size else 0, 0).astype(np.float32)
        return {"ids": ids, "weights": w, "count": count, "t_walk": self.t_walk.get()[:n],
                "t_sel": self.t_sel.get()[:n], "t_rem": self.t_rem.get()[:n]}



def check_pixels(pixels, width: int, height: int) -> np.ndarray:
    """pixels [P,2] integer (x, y) as a contiguous int32 array; ValueError if malformed or outside
    the width x height image."""
    arr = np.asarray(pixels)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"pixels must have shape [P, 2] (x, y), got {arr.shape}")
    if arr.size and not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"pixels must be integer coordinates, got dtype {arr.dtype}")
    arr = arr.astype(np.int64)
    bad = (arr[:, 0] < 0) | (arr[:, 0] >= width) | (arr[:, 1] < 0) | (arr[:, 1] >= height)
    if bad.any():
        x, y = arr[np.argmax(bad)]
        raise ValueError(f"{int(bad.sum())} pixel(s) outside the {width}x{height} image, e.g. ({x}, {y})")
    return np.ascontiguousarray(arr, np.int32)


def _transpose_counted(sel: Selection) -> Transpose:
    """CPU-shaped transpose (transpose_count / transpose_fill): a stable counting sort by a few
    long work-items, each owning a contiguous chunk of rays."""
    rt = sel.plan.runtime
    n, n_rays = sel.n_gaussians, sel.n_rays
    # enough chunks to keep every core busy, no more: each adds a cursor slot per Gaussian (64
    # chunks held 77 MB of cursor for 300k Gaussians; 8 on 2 cores, 9.6 MB, within 5 % of its time)
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
    return Transpose(cursor, t_ray, t_w, t_entry, chunks)


def _backward_order(sel: Selection, t: Transpose) -> cla.Array:
    """See :meth:`Selection.backward_order`."""
    plan = sel.plan
    ends = t.cursor.get().reshape(-1, t.chunks)[:, -1].astype(np.int64)
    starts = np.concatenate([[0], ends[:-1]])
    first = t.ray.get()[np.minimum(starts, t.ray.size - 1)]
    xy = (np.stack([first % plan.width, first // plan.width], 1) if sel.pixels is None
          else sel.pixels[np.minimum(first, max(len(sel.pixels) - 1, 0))])
    tile = np.where(ends > starts, (xy[:, 1] // TILE) * plan.tiles_x + xy[:, 0] // TILE, np.iinfo(np.int32).max)
    return to_device(plan.runtime, np.lexsort((first, tile)), np.int32)


@lru_cache(maxsize=None)
def _max_scan(context: cl.Context) -> InclusiveScanKernel:
    return InclusiveScanKernel(context, np.int32, "max(a, b)", "0")


def _transpose_sorted(sel: Selection) -> Transpose:
    """GPU-shaped transpose (transpose_keys -> device sort -> transpose_gather -> max-scan): one
    work-item per ray or entry; the same entries in the same order as :func:`_transpose_counted`,
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
        _max_scan(rt.context)(cursor)
    return Transpose(cursor, t_ray, t_w, t_entry, 1)


def ray_launch(plan: RasterPlan, pixels: np.ndarray | None) -> tuple[int, int]:
    """(global size, full-image flag) of a kernel with one work-item per ray (blend.cl): the whole
    image is launched tile-major over whole tiles (padding rays return at once), a pixel subset
    one work-item per pixel."""
    if pixels is None:
        return plan.tiles_x * plan.tiles_y * TILE * TILE, 1
    return len(pixels), 0


def ray_blocks(plan: RasterPlan, pixels: np.ndarray | None) -> tuple[int, dict]:
    """(global size, arguments) of a kernel with one work-item per block of rays (BLOCK_ARGS of
    kernels/common.h): the whole image in blocks of a tile row; a pixel subset grouped by tile
    (stable order) into blocks of at most TILE rays: blocks [B, 4] = (first, count, tile, 0) into
    order [P], the ray indices sorted by tile. B is a multiple of TILE, the work-group size of
    block kernels (:data:`BLOCK_GROUP`)."""
    rt = plan.runtime
    if pixels is None:
        unused = device_zeros(rt, 4, np.int32)
        return plan.tiles_x * plan.tiles_y * TILE, dict(plan.ray_args(), full=1, pixels=unused,
                                                          order=unused, blocks=unused)
    tile = (pixels[:, 1] // TILE) * plan.tiles_x + pixels[:, 0] // TILE
    order = np.argsort(tile, kind="stable").astype(np.int32)
    sorted_tile = tile[order]
    starts = np.flatnonzero(np.r_[True, sorted_tile[1:] != sorted_tile[:-1]])
    run_len = np.diff(np.r_[starts, len(order)])
    per_run = -(-run_len // TILE)                                   # blocks per run of one tile
    run = np.repeat(np.arange(len(starts)), per_run)                # the run of each block
    first = starts[run] + TILE * (np.arange(len(run)) - np.repeat(np.cumsum(per_run) - per_run, per_run))
    blocks = np.zeros((-(-len(run) // TILE) * TILE, 4), np.int64)   # padded with empty blocks
    blocks[:len(run), :3] = np.stack([first, np.minimum(TILE, starts[run] + run_len[run] - first),
                                      sorted_tile[first]], 1)
    return len(blocks), dict(plan.ray_args(), full=0, pixels=to_device(rt, pixels, np.int32),
                             order=to_device(rt, order, np.int32), blocks=to_device(rt, blocks, np.int32))


def check_sampler(sampler: str, k) -> int:
    """K as an int (0 for volume, which has none); ValueError for an unknown sampler or a K that
    is not an integer >= 1."""
    if sampler not in SAMPLERS:
        raise ValueError(f"sampler={sampler!r}: available samplers are {SAMPLERS}")
    if sampler == "volume":
        return 0
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise ValueError(f"k must be an integer >= 1 for sampler={sampler!r} (K must be at least one "
                         f"Gaussian per ray), got {k!r}")
    return int(k)


@lru_cache(maxsize=4)
def row_offsets(queue: cl.CommandQueue, n_rays: int, k: int) -> cla.Array:
    """The offsets [P] int32 p * K of a selection in rows of K slots, made once per (P, K) and
    shared by the selections that use them (never written: a whole image's took about 0.7 ms to
    fill per call, 6 % of the fox's K=10 selection)."""
    return cla.arange(queue, 0, n_rays * k, k, dtype=np.int32)


def entry_bytes(rt: Runtime) -> int:
    """Bytes per selection entry of the largest buffer made for it: an id (4), or on GPU-shaped
    runtimes what the transpose's device sort makes per key (:data:`SORT_BYTES_PER_KEY`), so a
    selection that fits also fits its backward."""
    return SORT_BYTES_PER_KEY if rt.gpu_shaped else 4


def select(plan: RasterPlan, sampler: str = "quantile", k: int = 40, pixels=None,
           defer: bool = False) -> Selection:
    """Run the selection kernel of ``sampler`` ("volume", "quantile", "topk" or "stratified") with
    K = ``k`` (ignored by volume) for the whole image or the rays ``pixels`` [P,2] (x, y) in px.

    Cost is proportional to the number of rays (and their tile lists), not to width * height.
    ``defer``: on CPU-shaped runtimes the K samplers' kernel is not enqueued yet but kept as the
    Selection's ``pending`` launch, so that the first :func:`qr_cl.stages.blend.blend_forward`
    runs it with the blend fused in (each ray blended right after it is selected: the same
    selection and image); call :meth:`Selection.ready` before any other use.
    """
    k = check_sampler(sampler, k)
    rt = plan.runtime
    q = rt.queue
    if pixels is not None:
        pixels = check_pixels(pixels, plan.width, plan.height)
    n_rays = plan.width * plan.height if pixels is None else len(pixels)
    # zeroed, so a ray that a driver's cut-short kernel left unwritten selects nothing
    count, t_walk, t_sel, t_rem = (device_zeros(rt, max(n_rays, 1), dt)
                                   for dt in (np.int32, np.float32, np.float32, np.float32))
    if n_rays == 0:
        return Selection(plan, sampler, k, pixels, device_empty(rt, 1, np.int32), device_empty(rt, 1, np.float32),
                         device_zeros(rt, 1, np.int32), count, t_walk, t_sel, t_rem)
    size, rays = ray_blocks(plan, pixels)
    if sampler == "volume":
        offsets = device_zeros(rt, n_rays, np.int32)
        rt.launch("volume_count", size, local_size=BLOCK_GROUP, **rays, count=count, t_walk=t_walk)
        exclusive_scan(rt, count, offsets)
        total = last_value(offsets) + last_value(count[:n_rays])
        check_buffer(rt, entry_bytes(rt) * total, f"the volume selection of {n_rays} rays ({total} entries)")
        ids, weights = device_empty(rt, max(total, 1), np.int32), device_empty(rt, max(total, 1), np.float32)
        rt.launch("volume_fill", size, local_size=BLOCK_GROUP, **rays, offsets=offsets, out_ids=ids,
                  out_w=weights,
                  t_sel=t_sel, t_rem=t_rem)
    else:
        check_buffer(rt, entry_bytes(rt) * n_rays * k, f"the {sampler} selection of {n_rays} rays x K={k}")
        ids, weights = device_empty(rt, n_rays * k, np.int32), device_empty(rt, n_rays * k, np.float32)
        offsets = row_offsets(q, n_rays, k)

        def launch(defines: dict | None = None, **blend_args) -> None:
            rt.launch(f"select_{sampler}", size, defines=defines, local_size=BLOCK_GROUP, **rays, K=k,
                      out_ids=ids, out_w=weights, count=count, t_walk=t_walk, t_sel=t_sel, t_rem=t_rem,
                      **blend_args)
        if defer and not rt.gpu_shaped:
            return Selection(plan, sampler, k, pixels, ids, weights, offsets, count, t_walk, t_sel, t_rem,
                             pending=launch)
        launch()
    return Selection(plan, sampler, k, pixels, ids, weights, offsets, count, t_walk, t_sel, t_rem)


def transmittance_profile(selection: Selection, ray: int) -> tuple[np.ndarray, np.ndarray]:
    """Transmittance along ray ``ray`` as its sampler sees it: (depths [n] of the selected
    Gaussians in camera z, T [n+1] before the first and after each selected Gaussian).

    volume: T_i of the full walk; quantile/topk: T^Q among the selected (un-normalized). This is
    what the paper's Fig. 3 plots (see :func:`qr_cl.app.images.plot_transmittance_profiles`).
    """
    h = selection.host()
    n = int(h["count"][ray])
    ids, w = h["ids"][ray, :n], h["weights"][ray, :n].astype(np.float64)
    scale = 1.0 if selection.sampler == "volume" else 1.0 - float(h["t_sel"][ray])
    t = 1.0 - np.concatenate([[0.0], np.cumsum(w * scale)])
    depths = selection.plan.splats.get().reshape(-1, 8)[ids, 6] if n else np.zeros(0, np.float32)
    return depths, t


# ----------------------------------------------------------------------------------------------
# subsets of rays and compact id tables (training: rays sampled from per-view selections, and
# features computed only for the Gaussians a step's selections use)
# ----------------------------------------------------------------------------------------------

def ray_entries(offsets: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Positions [E] int64 in ``ids`` / ``weights`` of every entry of the rays with these
    ``offsets`` and ``count`` [P] (host arrays of a Selection), ray by ray, in entry order."""
    count = np.asarray(count, np.int64)
    starts = np.repeat(np.asarray(offsets, np.int64) - (np.cumsum(count) - count), count)
    return starts + np.arange(int(count.sum()), dtype=np.int64)


def gather_rays(selection: Selection, rays) -> Selection:
    """The Selection of the rays ``rays`` [P] (integer indices into ``selection``'s rays; for a
    whole-image selection ray y * width + x), copied on the device: the same entries, weights and
    per-ray transmittances that :func:`select` computes for those pixels, so a view's whole-image
    selection, computed once, serves any subset of its rays.

    The result has ``pixels`` [P,2] (x, y) set; quantile/top-K keep dense rows of K (a ray's K
    slots copied whole, padding included), volume gets a fresh CSR list.
    """
    rays = np.asarray(rays)
    if rays.ndim != 1 or (rays.size and not np.issubdtype(rays.dtype, np.integer)):
        raise ValueError(f"rays must be a 1-D integer array, got {rays.dtype} {rays.shape}")
    rays = rays.astype(np.int64)
    n_all = selection.n_rays
    if rays.size and (rays.min() < 0 or rays.max() >= n_all):
        raise ValueError(f"rays must index the selection's {n_all} rays, got [{rays.min()}, {rays.max()}]")
    if selection.pixels is None:
        width = selection.plan.width
        pixels = np.stack([rays % width, rays // width], 1).astype(np.int32)
    else:
        pixels = np.ascontiguousarray(selection.pixels[rays], np.int32)
    rt = selection.plan.runtime
    n = len(rays)
    if n == 0:
        return Selection(selection.plan, selection.sampler, selection.k, pixels, device_empty(rt, 1, np.int32),
                         device_empty(rt, 1, np.float32), device_zeros(rt, 1, np.int32),
                         *(device_zeros(rt, 1, dt) for dt in (np.int32, np.float32, np.float32, np.float32)))
    k = selection.k
    if selection.sampler == "volume":
        all_offsets, all_count = selection.spans()
        count = all_count[rays]
        offsets = (np.cumsum(count) - count).astype(np.int32)
        source = ray_entries(all_offsets[rays], count)
    else:                                    # dense rows: ray p's K slots start at p * K
        offsets = np.arange(0, n * k, k, dtype=np.int32)
        source = (rays[:, None] * k + np.arange(k)).ravel()
    if source.size == 0:
        ids, weights = device_empty(rt, 1, np.int32), device_empty(rt, 1, np.float32)
    else:
        index = to_device(rt, source, np.int32)
        ids, weights = cla.take(selection.ids, index), cla.take(selection.weights, index)
    ray_index = to_device(rt, rays, np.int32)
    per_ray = [cla.take(a, ray_index) for a in (selection.count, selection.t_walk, selection.t_sel, selection.t_rem)]
    return Selection(selection.plan, selection.sampler, k, pixels, ids, weights, to_device(rt, offsets, np.int32),
                     *per_ray)


@dataclass
class CompactSelection(Selection):
    """A Selection whose entry ids index a compact table of ``n_rows`` rows (see
    :func:`compact_selections`) instead of the plan's Gaussians: blend it with features
    [n_rows, C]; the blend backward then returns dF [n_rows, C]."""

    n_rows: int = 0

    @property
    def n_gaussians(self) -> int:
        return self.n_rows


def remap_ids(selection: Selection, lut: np.ndarray, n_rows: int) -> CompactSelection:
    """``selection`` with every entry id g replaced by ``lut[g]`` (lut [N] integer, values in
    0..n_rows-1 for every Gaussian an entry uses), as a :class:`CompactSelection` of ``n_rows``
    rows sharing the other device arrays. Padding slots of dense rows become -1."""
    return _remap(selection, *_host_entries(selection), lut, n_rows)


def _host_entries(selection: Selection) -> tuple[np.ndarray, np.ndarray]:
    """(ids [len(selection.ids)] int32 on the host, positions [E] of the rays' entries in it)."""
    return selection.ids.get(), ray_entries(*selection.spans())


def _remap(selection: Selection, ids: np.ndarray, entries: np.ndarray, lut: np.ndarray,
           n_rows: int) -> CompactSelection:
    used = ids[entries]
    if used.size and (used.min() < 0 or used.max() >= len(lut)):
        raise ValueError(f"lut has {len(lut)} rows; the selection uses ids up to {used.max()}")
    mapped = np.asarray(lut)[used]
    if mapped.size and (mapped.min() < 0 or mapped.max() >= n_rows):
        raise ValueError(f"lut maps the selection's ids outside 0..{n_rows - 1}")
    remapped = np.full(ids.shape, -1, np.int32)
    remapped[entries] = mapped
    return CompactSelection(selection.plan, selection.sampler, selection.k, selection.pixels,
                            to_device(selection.plan.runtime, remapped, np.int32), selection.weights, selection.offsets, selection.count,
                            selection.t_walk, selection.t_sel, selection.t_rem, n_rows=int(n_rows))


def compact_selections(selections: list[Selection]) -> tuple[np.ndarray, list[CompactSelection]]:
    """The Gaussians that ``selections`` (of one scene: the same N) use, and the selections
    re-indexed into them: (rows [U] int64, the used Gaussian ids ascending; one
    :class:`CompactSelection` of U rows per input). Blending a compact selection with
    ``features[rows]`` [U,C] gives the image blending the original with ``features`` [N,C] gives
    (the same entries in the same order), and its backward's dF [U,C] are the rows ``rows`` of
    the original's dF (the others are zero)."""
    if not selections:
        return np.zeros(0, np.int64), []
    n = selections[0].n_gaussians
    if any(s.n_gaussians != n for s in selections):
        raise ValueError(f"selections of different scenes: N = {sorted({s.n_gaussians for s in selections})}")
    hosts = [_host_entries(s) for s in selections]
    used = np.zeros(n, bool)
    for ids, entries in hosts:
        used[ids[entries]] = True
    rows = np.flatnonzero(used)
    lut = (np.cumsum(used) - 1).astype(np.int32)
    return rows, [_remap(s, ids, entries, lut, len(rows)) for s, (ids, entries) in zip(selections, hosts)]


def concat_selections(selections: list[Selection]) -> Selection:
    """The rays of several pixel-subset selections over the same Gaussians (e.g. a training step's
    views of one scene, same sampler and K) one after the other, as one Selection: ray i of part j
    is ray (rays of parts before j) + i, with the same entries, weights and transmittances, so one
    blend (and one backward, one transpose) serves them all and its image rows are the parts'
    images stacked. The result keeps the first part's plan (runtime, N) and every part's
    ``pixels`` (each in its own view's image); it is a CompactSelection when the parts are."""
    if not selections:
        raise ValueError("no selections to concatenate")
    first = selections[0]
    if any(s.pixels is None for s in selections):
        raise ValueError("concat_selections takes pixel subsets (gather_rays makes one from a whole image)")
    if any((s.sampler, s.k, s.n_gaussians, type(s)) != (first.sampler, first.k, first.n_gaussians, type(first))
           for s in selections):
        raise ValueError("the selections differ in sampler, K, Gaussians or kind")
    parts = [s for s in selections if s.n_rays]
    if not parts:
        return first
    q = first.plan.runtime.queue
    base = np.cumsum([0] + [s.ids.shape[0] for s in parts[:-1]])
    offsets = np.concatenate([s.offsets.get()[:s.n_rays] + b for s, b in zip(parts, base)]).astype(np.int32)
    entries = {name: cla.concatenate([getattr(s, name) for s in parts], queue=q) for name in ("ids", "weights")}
    per_ray = {name: cla.concatenate([getattr(s, name)[:s.n_rays] for s in parts], queue=q)
               for name in ("count", "t_walk", "t_sel", "t_rem")}
    extra = {"n_rows": first.n_rows} if isinstance(first, CompactSelection) else {}
    return type(first)(first.plan, first.sampler, first.k, np.concatenate([s.pixels for s in parts]),
                       offsets=to_device(first.plan.runtime, offsets, np.int32), **entries, **per_ray, **extra)
