"""Selections made from selections, beside :class:`~qr_cl.stages.select.Selection`: subsets of a
view's rays gathered from its whole-image selection, several views' rays as one selection, ids
re-indexed into a compact table of the Gaussians some rays use (a training step computes features
for those rows only), and a selection of given per-ray lists (registration's top contributors).
Each is made by :func:`derived` from the selection it comes from, but :func:`listed_selection`.
Device arrays come from the runtime's pool. Twins: tests/stages/test_selections.py."""
from __future__ import annotations

import dataclasses

import numpy as np
import pyopencl.array as cla

from ..runtime import Runtime, device_empty, device_zeros, to_device
from .binning import RasterPlan
from .select import Selection, check_pixels


def derived(source: Selection, **fields) -> Selection:
    """A new Selection of ``source``'s plan, sampler and K with ``fields`` (keyword-only: any of
    pixels, ids, weights, offsets, count, t_walk, t_sel, t_rem and n_rows, as
    :class:`qr_cl.stages.Selection` documents them) in place of its own, the others shared. A compact selection (``n_rows`` set) indexes a table of
    n_rows rows (:func:`compact_selections`): blend it with features [n_rows, C]; its blend
    backward returns dF [n_rows, C]."""
    fixed = {"plan", "sampler", "k"} & fields.keys()
    if fixed:
        raise ValueError(f"a derived selection keeps its source's {sorted(fixed)}")
    return dataclasses.replace(source, **fields)


def ray_entries(offsets: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Positions [E] int64 in ``ids`` / ``weights`` of every entry of the rays with these
    ``offsets`` and ``count`` [P] (host arrays of a Selection), ray by ray, in entry order."""
    count = np.asarray(count, np.int64)
    starts = np.repeat(np.asarray(offsets, np.int64) - (np.cumsum(count) - count), count)
    return starts + np.arange(int(count.sum()), dtype=np.int64)


def _take(rt: Runtime, array: cla.Array, index: cla.Array) -> cla.Array:
    """``array[index]`` [len(index)] in a device array from ``rt``'s pool."""
    return cla.take(array, index, out=device_empty(rt, index.shape, array.dtype))


def _concatenate(rt: Runtime, arrays: list[cla.Array]) -> cla.Array:
    """The 1-D device ``arrays`` (one dtype) one after the other, in a device array from ``rt``'s pool."""
    out = device_empty(rt, sum(a.size for a in arrays), arrays[0].dtype)
    start = 0
    for a in arrays:
        out[start:start + a.size] = a
        start += a.size
    return out


def gather_rays(selection: Selection, rays) -> Selection:
    """The Selection of the rays ``rays`` [P] (integer indices into ``selection``'s rays; for a
    whole-image selection ray y * width + x), copied on the device: the same entries, weights and
    per-ray transmittances that :func:`qr_cl.stages.select` computes for those pixels, so a view's
    whole-image selection, computed once, serves any subset of its rays.

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
        count, t_walk, t_sel, t_rem = (device_zeros(rt, 1, dt) for dt in (np.int32, np.float32, np.float32, np.float32))
        return derived(selection, pixels=pixels, ids=device_empty(rt, 1, np.int32),
                       weights=device_empty(rt, 1, np.float32), offsets=device_zeros(rt, 1, np.int32), count=count,
                       t_walk=t_walk, t_sel=t_sel, t_rem=t_rem)
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
        ids, weights = _take(rt, selection.ids, index), _take(rt, selection.weights, index)
    ray_index = to_device(rt, rays, np.int32)
    per_ray = {name: _take(rt, getattr(selection, name), ray_index) for name in ("count", "t_walk", "t_sel", "t_rem")}
    return derived(selection, pixels=pixels, ids=ids, weights=weights, offsets=to_device(rt, offsets, np.int32),
                   **per_ray)


def remap_ids(selection: Selection, lut: np.ndarray, n_rows: int) -> Selection:
    """``selection`` with every entry id g replaced by ``lut[g]`` (lut [N] integer, values in
    0..n_rows-1 for every Gaussian an entry uses), as a compact selection of ``n_rows`` rows
    (:func:`derived`) sharing the other device arrays. Padding slots of dense rows become -1."""
    return _remap(selection, *_host_entries(selection), lut, n_rows)


def _host_entries(selection: Selection) -> tuple[np.ndarray, np.ndarray]:
    """(ids [len(selection.ids)] int32 on the host, positions [E] of the rays' entries in it)."""
    return selection.ids.get(), ray_entries(*selection.spans())


def _remap(selection: Selection, ids: np.ndarray, entries: np.ndarray, lut: np.ndarray,
           n_rows: int) -> Selection:
    used = ids[entries]
    if used.size and (used.min() < 0 or used.max() >= len(lut)):
        raise ValueError(f"lut has {len(lut)} rows; the selection uses ids up to {used.max()}")
    mapped = np.asarray(lut)[used]
    if mapped.size and (mapped.min() < 0 or mapped.max() >= n_rows):
        raise ValueError(f"lut maps the selection's ids outside 0..{n_rows - 1}")
    remapped = np.full(ids.shape, -1, np.int32)
    remapped[entries] = mapped
    return derived(selection, ids=to_device(selection.plan.runtime, remapped, np.int32), n_rows=int(n_rows))


def compact_selections(selections: list[Selection]) -> tuple[np.ndarray, list[Selection]]:
    """The Gaussians that ``selections`` (of one scene: the same N) use, and the selections
    re-indexed into them: (rows [U] int64, the used Gaussian ids ascending; one compact selection
    of U rows per input). Blending a compact selection with
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
    ``pixels`` (each in its own view's image); it is compact when the parts are (of one n_rows)."""
    if not selections:
        raise ValueError("no selections to concatenate")
    first = selections[0]
    if any(s.pixels is None for s in selections):
        raise ValueError("concat_selections takes pixel subsets (gather_rays makes one from a whole image)")
    if any((s.sampler, s.k, s.n_gaussians, s.n_rows is None) != (first.sampler, first.k, first.n_gaussians,
                                                                  first.n_rows is None) for s in selections):
        raise ValueError("the selections differ in sampler, K, Gaussians or kind")
    parts = [s for s in selections if s.n_rays]
    if not parts:
        return first
    rt = first.plan.runtime
    base = np.cumsum([0] + [s.ids.shape[0] for s in parts[:-1]])
    offsets = np.concatenate([s.offsets.get()[:s.n_rays] + b for s, b in zip(parts, base)]).astype(np.int32)
    entries = {name: _concatenate(rt, [getattr(s, name) for s in parts]) for name in ("ids", "weights")}
    per_ray = {name: _concatenate(rt, [getattr(s, name)[:s.n_rays] for s in parts])
               for name in ("count", "t_walk", "t_sel", "t_rem")}
    return derived(first, pixels=np.concatenate([s.pixels for s in parts]), offsets=to_device(rt, offsets, np.int32),
                   **entries, **per_ray)


def listed_selection(plan: RasterPlan, pixels: np.ndarray, ids: np.ndarray, weights: np.ndarray,
                     n_rows: int | None = None) -> Selection:
    """A Selection of the rays ``pixels`` [P,2] (x, y) of ``plan`` with the given lists: ids [P,L]
    int (Gaussians, or rows of a compact table of ``n_rows`` rows; -1 in slots past a ray's list,
    which come last) and weights [P,L] float32, as dense rows of L (sampler "topk", K = L). Its
    transmittances are zero: it is made for its entries (a blend, or its feature backward), not
    for its background or alpha."""
    pixels = check_pixels(pixels, plan.width, plan.height)
    ids, weights = np.asarray(ids), np.asarray(weights, np.float32)
    if ids.ndim != 2 or ids.shape != weights.shape or len(ids) != len(pixels):
        raise ValueError(f"ids and weights must both be [{len(pixels)}, L] (one row per pixel), got "
                         f"{ids.shape} and {weights.shape}")
    rt = plan.runtime
    n_rays, k = ids.shape

    def device(values: np.ndarray, dtype) -> cla.Array:     # at least one slot, as select's arrays
        return to_device(rt, values.ravel() if values.size else np.zeros(1), dtype)
    t_walk, t_sel, t_rem = (device_zeros(rt, max(n_rays, 1), np.float32) for _ in range(3))
    return Selection(plan=plan, sampler="topk", k=k, pixels=pixels, ids=device(np.where(ids >= 0, ids, -1), np.int32),
                     weights=device(weights, np.float32), offsets=device(np.arange(n_rays) * k, np.int32),
                     count=device((ids >= 0).sum(1), np.int32), t_walk=t_walk, t_sel=t_sel, t_rem=t_rem,
                     n_rows=n_rows)
