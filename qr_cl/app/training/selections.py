"""Selections as a training step uses them: subsets of a view's rays gathered from its whole-image
selection, several views' rays as one selection, and ids re-indexed into a compact table of the
Gaussians a step uses (features are computed for those rows only). Device arrays come from the
runtime's pool."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyopencl.array as cla

from ...runtime import Runtime, device_empty, device_zeros, to_device
from ...stages import Selection


@dataclass
class CompactSelection(Selection):
    """A Selection whose entry ids index a compact table of ``n_rows`` rows (see
    :func:`compact_selections`) instead of the plan's Gaussians: blend it with features
    [n_rows, C]; the blend backward then returns dF [n_rows, C]."""

    n_rows: int = 0

    @property
    def n_gaussians(self) -> int:
        return self.n_rows


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
        ids, weights = _take(rt, selection.ids, index), _take(rt, selection.weights, index)
    ray_index = to_device(rt, rays, np.int32)
    per_ray = [_take(rt, a, ray_index) for a in (selection.count, selection.t_walk, selection.t_sel, selection.t_rem)]
    return Selection(selection.plan, selection.sampler, k, pixels, ids, weights, to_device(rt, offsets, np.int32),
                     *per_ray)


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
                            to_device(selection.plan.runtime, remapped, np.int32), selection.weights,
                            selection.offsets, selection.count, selection.t_walk, selection.t_sel, selection.t_rem,
                            n_rows=int(n_rows))


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
    rt = first.plan.runtime
    base = np.cumsum([0] + [s.ids.shape[0] for s in parts[:-1]])
    offsets = np.concatenate([s.offsets.get()[:s.n_rays] + b for s, b in zip(parts, base)]).astype(np.int32)
    entries = {name: _concatenate(rt, [getattr(s, name) for s in parts]) for name in ("ids", "weights")}
    per_ray = {name: _concatenate(rt, [getattr(s, name)[:s.n_rays] for s in parts])
               for name in ("count", "t_walk", "t_sel", "t_rem")}
    extra = {"n_rows": first.n_rows} if isinstance(first, CompactSelection) else {}
    return type(first)(first.plan, first.sampler, first.k, np.concatenate([s.pixels for s in parts]),
                       offsets=to_device(rt, offsets, np.int32), **entries, **per_ray, **extra)
