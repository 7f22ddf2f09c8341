"""Selection stage (select.cl): which Gaussians each ray blends, with what weight.

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

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

from ..runtime import (BLOCK_GROUP, DEFAULTS, SAMPLERS, TILE, WALK_STATE_FLOATS, WALK_STATE_INTS, Runtime, check_buffer,
                       device_empty, device_zeros, exclusive_scan, last_value, to_device, walk_windows)
from .binning import SORT_BYTES_PER_KEY, RasterPlan

@dataclass(frozen=True, kw_only=True, eq=False)
class Selection:
    """Per-ray (Gaussian id, weight) lists on the device: a value, made by :func:`select` or
    :func:`qr_cl.stages.blend.select_and_blend` (or derived from one: :mod:`qr_cl.stages.selections`),
    constructed by keyword only, complete when returned.

    The contract: its fields are never reassigned (frozen), and no stage writes into it or its
    arrays once the selection kernel has run; the stages that read it (blend, transpose) return
    what they make of it (the transpose, the backward's owner bounds:
    :class:`qr_cl.stages.blend.BackwardIndex`) to their caller, which keeps it beside the selection.
    Equality is identity (two selections are the same only if they are one object).

    Rays: the whole image (``pixels is None``, ray p = y * width + x) or a pixel subset
    (``pixels`` [P,2] int32 (x, y), ray p = row p). Entries of ray p are
    ``[offsets[p], offsets[p] + count[p])`` of ``ids`` / ``weights`` (int32 / float32; quantile
    and topk: dense rows of K at p * K, padded with -1 / 0). Per ray (float32 [P]): ``t_walk`` the
    transmittance where the ray's walk stopped, ``t_sel`` the transmittance among the selected
    Gaussians before normalization (T^Q; the final T for volume), ``t_rem`` the background weight.
    ``k`` is K (0 for volume). The ids index a table of :attr:`n_gaussians` rows: the plan's N
    Gaussians, or ``n_rows`` rows when set (a compact table of the Gaussians some rays use).
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
    n_rows: int | None = None

    @property
    def n_rays(self) -> int:
        return self.plan.width * self.plan.height if self.pixels is None else len(self.pixels)

    @property
    def n_gaussians(self) -> int:
        """The rows of the table the ids index: ``n_rows``, or the plan's N."""
        return self.plan.n_gaussians if self.n_rows is None else self.n_rows

    @property
    def nbytes(self) -> int:
        """Device bytes held by the selection's arrays."""
        return sum(a.nbytes for a in (self.ids, self.weights, self.offsets, self.count, self.t_walk, self.t_sel,
                                      self.t_rem))

    def launch(self) -> tuple[int, int]:
        """(global size of a per-ray kernel, full-image flag)."""
        return ray_launch(self.plan, self.pixels)

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


def ray_launch(plan: RasterPlan, pixels: np.ndarray | None) -> tuple[int, int]:
    """(global size, full-image flag) of a kernel with one work-item per ray (blend.cl): the whole
    image is launched tile-major over whole tiles (padding rays return at once), a pixel subset
    one work-item per pixel."""
    if pixels is None:
        return plan.tiles_x * plan.tiles_y * TILE * TILE, 1
    return len(pixels), 0


def ray_blocks(plan: RasterPlan, pixels: np.ndarray | None, per_block: int, pad_to: int = 1) -> tuple[int, dict]:
    """(blocks, arguments) of a kernel walking rays in blocks of up to ``per_block`` rays of one
    tile (BLOCK_ARGS of kernels/walk.h): the whole image in blocks of per_block consecutive
    pixels of a tile (a tile row for the block walk, a tile or part of one for the tile walk:
    ``tiles * TILE * TILE / per_block`` blocks); a pixel subset grouped by tile (stable order) into
    blocks of at most per_block rays: blocks [B, 4] = (first, count, tile, 0) into order [P], the
    ray indices sorted by tile, B padded with empty blocks to a multiple of ``pad_to``."""
    rt = plan.runtime
    if pixels is None:
        unused = device_zeros(rt, 4, np.int32)
        return plan.tiles_x * plan.tiles_y * TILE * TILE // per_block, dict(
            plan.ray_args(), full=1, pixels=unused, order=unused, blocks=unused)
    tile = (pixels[:, 1] // TILE) * plan.tiles_x + pixels[:, 0] // TILE
    order = np.argsort(tile, kind="stable").astype(np.int32)
    sorted_tile = tile[order]
    starts = np.flatnonzero(np.r_[True, sorted_tile[1:] != sorted_tile[:-1]])
    run_len = np.diff(np.r_[starts, len(order)])
    per_run = -(-run_len // per_block)                              # blocks per run of one tile
    run = np.repeat(np.arange(len(starts)), per_run)                # the run of each block
    first = starts[run] + per_block * (np.arange(len(run)) - np.repeat(np.cumsum(per_run) - per_run, per_run))
    blocks = np.zeros((-(-len(run) // pad_to) * pad_to, 4), np.int64)
    blocks[:len(run), :3] = np.stack([first, np.minimum(per_block, starts[run] + run_len[run] - first),
                                      sorted_tile[first]], 1)
    return len(blocks), dict(plan.ray_args(), full=0, pixels=to_device(rt, pixels, np.int32),
                             order=to_device(rt, order, np.int32), blocks=to_device(rt, blocks, np.int32))


def step_loops(rt: Runtime, sampler: str, k: int) -> int:
    """The loop iterations a selection kernel's work-item may make per list position it walks (the
    unit of :func:`qr_cl.runtime.walk_windows`), at most: the tile walk's batch loops plus, per
    position, Q-Render's boundary search (up to K), top-K's heap (2 log2 K); the block walk's the
    same for each of its TILE lanes, with the lane loops around them."""
    heap = 2 * max(k, 1).bit_length() + 4
    if rt.gpu_shaped:
        return {"quantile": k + 4, "stratified": k + 4, "topk": heap, "volume": 4}[sampler]
    return {"quantile": 4 * TILE + 2 * k + 8, "stratified": 4 * TILE + 2 * k + 8, "topk": TILE * heap,
            "volume": TILE + 4}[sampler]


class Walk:
    """How a runtime walks the tile lists of a plan for a selection kernel: the block walk (CPU
    shapes: kernel ``name``, work-groups of BLOCK_GROUP blocks of TILE rays) or the tile walk (GPU
    shapes: kernel ``tile_<name>``, a work-group of GROUP_RAYS rays per block), in the windows
    :func:`qr_cl.runtime.walk_windows` gives, with the rays' walk state between windows in
    ``state_f`` [P, WALK_STATE_FLOATS] float32 and ``state_i`` [P, WALK_STATE_INTS] int32 (fields
    named by :class:`qr_cl.runtime.WalkStateLayout`; one slot each when one window)."""

    def __init__(self, plan: RasterPlan, pixels: np.ndarray | None, n_rays: int, loops: int) -> None:
        rt = self.rt = plan.runtime
        self.per_block = rt.group_rays if rt.gpu_shaped else TILE
        self.blocks, self.rays = ray_blocks(plan, pixels, self.per_block, 1 if rt.gpu_shaped else BLOCK_GROUP[0])
        self.windows = walk_windows(rt.loop_limit, plan.longest_list if rt.loop_limit else 0, loops)
        slots = n_rays if len(self.windows) > 1 else 1
        self.state = dict(state_f=device_empty(rt, slots * WALK_STATE_FLOATS, np.float32),
                          state_i=device_empty(rt, slots * WALK_STATE_INTS, np.int32))

    def launch(self, name: str, defines: dict | None = None, windows: list | None = None, **args) -> None:
        """Run kernel ``name`` (its block or tile walk) over every window (or ``windows``)."""
        kernel, local = (f"tile_{name.removeprefix('select_')}", (self.per_block,)) if self.rt.gpu_shaped \
            else (name, BLOCK_GROUP)
        for walk_from, walk_to in self.windows if windows is None else windows:
            self.rt.launch(kernel, self.blocks * local[0] if self.rt.gpu_shaped else self.blocks, defines=defines,
                           local_size=local, **self.rays, walk_from=walk_from, walk_to=walk_to, **self.state, **args)


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
    shared by the selections that use them (never written: filling a whole image's anew on every
    call was a visible share of a selection)."""
    return cla.arange(queue, 0, n_rays * k, k, dtype=np.int32)


def entry_bytes(rt: Runtime) -> int:
    """Bytes per selection entry of the largest buffer made for it: an id (4), or on GPU-shaped
    runtimes what the transpose's device sort makes per key (:data:`SORT_BYTES_PER_KEY`), so a
    selection that fits also fits its backward."""
    return SORT_BYTES_PER_KEY if rt.gpu_shaped else 4


@dataclass(frozen=True, eq=False)
class SelectionKernel:
    """The selection kernel of a Selection from :func:`pending_select`, not yet enqueued: the
    walk of ``sampler`` over the selection's rays writing ``outputs`` (its device arrays). The
    stage that asked for it enqueues it once, alone (:meth:`run`, :func:`select`) or with a blend
    fused in (:func:`qr_cl.stages.blend.select_and_blend`), before it returns the selection."""

    walk: Walk
    sampler: str
    outputs: dict

    def run(self, defines: dict | None = None, **blend_args) -> None:
        """Enqueue the kernel (``defines`` and ``blend_args``: the build and arguments of a fused
        blend, none for the selection alone). Kernels and reads enqueued after it see the
        selection (the queue is in order)."""
        walk, outputs = self.walk, self.outputs
        if self.sampler != "stratified":
            walk.launch(f"select_{self.sampler}", defines, **outputs, **blend_args)
        elif len(walk.windows) == 1:                  # both walks in one launch
            walk.launch("select_stratified", defines, **outputs, **blend_args, **{"pass": 0})
        else:
            for pass_ in (1, 2):
                walk.launch("select_stratified", defines, **outputs, **blend_args, **{"pass": pass_})


def select(plan: RasterPlan, sampler: str = DEFAULTS.sampler, k: int = DEFAULTS.k, pixels=None) -> Selection:
    """Run the selection kernel of ``sampler`` ("volume", "quantile", "topk" or "stratified") with
    K = ``k`` (ignored by volume) for the whole image or the rays ``pixels`` [P,2] (x, y) in px.

    Cost is proportional to the number of rays (and their tile lists), not to width * height.
    """
    selection, kernel = pending_select(plan, sampler, k, pixels)
    if kernel is not None:
        kernel.run()
    return selection


def pending_select(plan: RasterPlan, sampler: str, k: int, pixels=None) -> tuple[Selection, SelectionKernel | None]:
    """The two selection stages' common part (:func:`select`, :func:`qr_cl.stages.blend.select_and_blend`),
    which they alone call: (the Selection, its :class:`SelectionKernel` not yet enqueued) for the
    K samplers on CPU-shaped runtimes without a loop limit, where a blend can be fused into the
    kernel (each ray blended right after it is selected: the same selection and image); else
    (the Selection made, None). The Selection must not be read, nor returned by the stage, before
    its kernel has run."""
    k = check_sampler(sampler, k)
    rt = plan.runtime
    q = rt.queue
    if pixels is not None:
        pixels = check_pixels(pixels, plan.width, plan.height)
    n_rays = plan.width * plan.height if pixels is None else len(pixels)
    # zeroed, so a ray that a driver's cut-short kernel left unwritten selects nothing
    count, t_walk, t_sel, t_rem = (device_zeros(rt, max(n_rays, 1), dt)
                                   for dt in (np.int32, np.float32, np.float32, np.float32))
    rays = dict(plan=plan, sampler=sampler, k=k, pixels=pixels, count=count, t_walk=t_walk, t_sel=t_sel, t_rem=t_rem)
    if n_rays == 0:
        return Selection(**rays, ids=device_empty(rt, 1, np.int32), weights=device_empty(rt, 1, np.float32),
                         offsets=device_zeros(rt, 1, np.int32)), None
    walk = Walk(plan, pixels, n_rays, step_loops(rt, sampler, k))
    if sampler == "volume":
        offsets = device_zeros(rt, n_rays, np.int32)
        walk.launch("volume_count", count=count, t_walk=t_walk)
        exclusive_scan(rt, count, offsets)
        total = last_value(offsets) + last_value(count[:n_rays])
        check_buffer(rt, entry_bytes(rt) * total, f"the volume selection of {n_rays} rays ({total} entries)")
        ids, weights = device_empty(rt, max(total, 1), np.int32), device_empty(rt, max(total, 1), np.float32)
        walk.launch("volume_fill", offsets=offsets, out_ids=ids, out_w=weights, t_sel=t_sel, t_rem=t_rem)
        return Selection(**rays, ids=ids, weights=weights, offsets=offsets), None
    check_buffer(rt, entry_bytes(rt) * n_rays * k, f"the {sampler} selection of {n_rays} rays x K={k}")
    ids, weights = device_empty(rt, n_rays * k, np.int32), device_empty(rt, n_rays * k, np.float32)
    kernel = SelectionKernel(walk, sampler, dict(K=k, out_ids=ids, out_w=weights, count=count, t_walk=t_walk,
                                                 t_sel=t_sel, t_rem=t_rem))
    selection = Selection(**rays, ids=ids, weights=weights, offsets=row_offsets(q, n_rays, k))
    if rt.gpu_shaped or rt.loop_limit is not None:
        kernel.run()
        return selection, None
    return selection, kernel
