"""Blend stage (blend.cl): a Selection blended with per-Gaussian features, and the backward
w.r.t. the features over the selection's transpose. Twin: :mod:`qr_cl.stages.blend_ref`.

Features and images are device rows of ``cstride`` floats (:func:`qr_cl.runtime.channel_layout`).
Both functions write into ``out`` when given one (e.g. a :func:`qr_cl.runtime.shared_array` over
a host array: the result then lands in host memory without a copy on CPU devices), else into a
device array from the runtime's pool.

A table larger than one device buffer is taken in row parts (:func:`qr_cl.runtime.row_parts`):
the functions that read or write table rows take the part's first row ``row0`` and its rows;
the image is the sum of the parts' blends (``accumulate``), the feature gradient of a part is its
rows of dF, and the geometry backward sums dL/dw of every part's entries (:func:`weight_grads`)
before :func:`blend_backward_alpha`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pyopencl.array as cla

from ..runtime import (SPLAT_FLOATS, TILE, Runtime, channel_layout, check_buffer, device_empty, device_zeros,
                       padded_vector, streamed, to_device, walk_windows)
from .binning import RasterPlan
from .select import Selection, pending_select
from .transpose import Transpose, backward_order, longest_segment, transpose

OWNERS_PER_CORE = 1   # the CPU backward scatter's work-items per compute unit
GPU_VW = 4            # GPU blends: floats of a row per work-item (a 16-byte load)
#: Loop iterations per entry (the walk windows' unit, :func:`qr_cl.runtime.walk_windows`) of the
#: gathers over a Gaussian's entries (a row vector per work-item, or group_blend's staging and
#: sums) and of splat_backward; weight_grads adds a loop over a row's vectors.
GATHER_LOOPS, SPLAT_LOOPS = 4, 2
OWNER_BINS = 4096     # ... whose Gaussian ranges are cut from a histogram of this many bins
CPU_GROUP_ROWS = TILE  # CPU shapes: blend work-groups of a tile row of rays (or dF rows) x all chunks


def _check_rows(array: cla.Array, rows: int, cstride: int, name: str, half: bool = False) -> None:
    if array.shape != (rows, cstride) or array.dtype not in ((np.float32, np.float16) if half else (np.float32,)):
        raise ValueError(f"{name} must be {'float32 or float16' if half else 'float32'} [{rows}, {cstride}] "
                         f"on the device, got {array.dtype} {array.shape}")


def _check_part(sel: Selection, row0: int, n_rows: int, name: str) -> None:
    """ValueError unless the rows [row0, row0 + n_rows) lie within the selection's Gaussians."""
    if row0 < 0 or n_rows < 0 or row0 + n_rows > sel.n_gaussians:
        raise ValueError(f"{name} must be rows of the {sel.n_gaussians} Gaussians, got rows [{row0}, "
                         f"{row0 + n_rows})")


def _check_entries(array: cla.Array, sel: Selection, name: str) -> None:
    """ValueError unless ``array`` is float32 with one value per selection entry (``sel.ids``'s shape)."""
    if array.shape != sel.ids.shape or array.dtype != np.float32:
        raise ValueError(f"{name} must be float32 {sel.ids.shape} (an entry's), got {array.dtype} {array.shape}")


@dataclass(eq=False)
class BackwardIndex:
    """What the backward of one Selection reads besides it, made on first use and kept by the
    selection's holder (the engine's cache entry or autograd Function, a training step), never by
    the Selection: its transpose (:func:`qr_cl.stages.transpose.transpose`, None until made) and
    the backward scatter's owner bounds by (number of owners, first row, rows) of a row part
    (:func:`owner_bounds`). Pass the same index to every backward call of the selection."""

    transposed: Transpose | None = None
    owners: dict[tuple[int, int, int], cla.Array] = field(default_factory=dict)

    def transpose(self, sel: Selection) -> Transpose:
        """The transpose of ``sel`` (made now if it is not yet)."""
        if self.transposed is None:
            self.transposed = transpose(sel)
        return self.transposed

    @property
    def nbytes(self) -> int:
        """Device bytes held."""
        return (0 if self.transposed is None else self.transposed.nbytes) + sum(a.nbytes for a in self.owners.values())


def row_defines(features: cla.Array) -> dict:
    """The build defines of a kernel that reads the feature table ``features``: ``HALF_ROWS``
    for a float16 table (read as half, blended in float: kernels/rows.h), none for float32."""
    return {"HALF_ROWS": 1} if features.dtype == np.float16 else {}


def work_groups(rt: Runtime, rows: int, n_chunks: int) -> tuple[int, tuple[int, int] | None]:
    """(global rows, local size) of a CPU-shaped blend kernel over ``rows`` x ``n_chunks``
    work-items: work-groups of CPU_GROUP_ROWS rows x all chunks (rows padded; the kernels return
    past their count), so that PoCL keeps at most that many work-items' accumulators (up to 2 KB
    each) on a thread's stack; too large groups are left to the runtime."""
    if CPU_GROUP_ROWS * n_chunks > rt.group_limit:
        return rows, None
    return -(-rows // CPU_GROUP_ROWS) * CPU_GROUP_ROWS, (CPU_GROUP_ROWS, n_chunks)


def group_shape(rt: Runtime, rows: int, cstride: int) -> tuple[dict, tuple[int, int], tuple[int, int]]:
    """(defines, global size, local size) of a GPU blend kernel (blend_group, blend_backward_group)
    over ``rows`` rows of ``cstride`` floats: work-items along a row's vectors of GPU_VW floats
    (the first dimension: neighbours read neighbouring floats of a row) x rows, in work-groups of
    Runtime.blend_group work-items, both dimensions padded (the kernels leave the padding idle)."""
    vw = min(GPU_VW, cstride)
    n_vec = cstride // vw
    lc = min(n_vec, rt.blend_group)
    lr = max(1, rt.blend_group // lc)
    return {"VW": vw, "NV": 1}, (-(-n_vec // lc) * lc, -(-rows // lr) * lr), (lc, lr)


def longest_entries(sel: Selection) -> int:
    """The most entries of one ray of ``sel`` (read from the device): how far a walk over a ray's
    entries goes."""
    return int(sel.spans()[1].max(initial=0))


def _image(rt: Runtime, n_rays: int, features: cla.Array, cstride: int, out: cla.Array | None) -> cla.Array:
    """The image [n_rays, cstride] float32 a blend of ``features`` (checked: float32 or float16
    rows of cstride) writes: ``out`` (checked) or a device array from the runtime's pool."""
    _check_rows(features, features.shape[0], cstride, "features", half=True)
    check_buffer(rt, 4 * n_rays * cstride, f"the image of {n_rays} rays x {cstride} channels")
    image = device_empty(rt, (n_rays, cstride), np.float32) if out is None else out
    _check_rows(image, n_rays, cstride, "out")
    return image


def _background(rt: Runtime, background: np.ndarray | None, channels: int, cstride: int, image: cla.Array) -> dict:
    """The blend kernels' background arguments (and whether the image is written streaming)."""
    return dict(background=to_device(rt, padded_vector(background, channels, cstride)),
                use_bg=background is not None, stream=streamed(image.nbytes))


def blend_forward(sel: Selection, features: cla.Array, channels: int,
                  background: np.ndarray | None = None, out: cla.Array | None = None, row0: int = 0,
                  accumulate: bool = False) -> cla.Array:
    """image [P, cstride] = sum_j w[p,j] features[id[p,j]] (+ t_rem[p] * background).

    features: float32 or float16 [R, cstride] device rows (cstride from channel_layout(channels);
    a float16 table is read as half and blended in float32): the table's rows [row0, row0 + R),
    all N of them or a row part (entries of other Gaussians are skipped);
    background: [channels] or None (no background term); out: an optional float32 [P, cstride]
    device array to write into (else one from the runtime's memory pool); ``accumulate``: add the
    blend to ``out`` (the parts after the first).
    Rays as in the Selection; for the full image row p = y * width + x.
    """
    rt = sel.plan.runtime
    vw, nv, cstride = channel_layout(channels, rt.narrow_rows)
    _check_part(sel, row0, features.shape[0], "features")
    if accumulate and out is None:
        raise ValueError("blend_forward(accumulate=True) adds to an image: pass it as out")
    image = _image(rt, sel.n_rays, features, cstride, out)
    if sel.n_rays == 0:
        return image
    size, full = sel.launch()
    plan = sel.plan
    args = dict(offsets=sel.offsets, count=sel.count, n_entries=sel.ids.size, sel_ids=sel.ids, sel_w=sel.weights,
                features=features, row0=row0, n_rows=features.shape[0], cstride=cstride, full=full,
                n_rays=sel.n_rays, width=plan.width, height=plan.height, tiles_x=plan.tiles_x, t_rem=sel.t_rem,
                accumulate=accumulate, image=image, **_background(rt, background, channels, cstride, image))
    if rt.gpu_shaped:
        defines, size2, local = group_shape(rt, size, cstride)
        rt.launch("blend_group", size2, defines={**defines, **row_defines(features)}, local_size=local, **args)
        return image
    n_chunks = cstride // (vw * nv)
    # CPU shapes: for whole images a group's rays are a tile row, whose feature rows stay in cache
    # over its chunks; always, the groups keep PoCL's per-group private arrays small
    size, local = work_groups(rt, size, n_chunks)
    rt.launch("blend", (size, n_chunks), defines={"VW": vw, "NV": nv, **row_defines(features)}, local_size=local,
              **args)
    return image


def select_and_blend(plan: RasterPlan, sampler: str, k: int, pixels: np.ndarray | None, features: cla.Array,
                     channels: int, background: np.ndarray | None = None,
                     out: cla.Array | None = None) -> tuple[Selection, cla.Array]:
    """The selection of ``sampler`` with K = ``k`` for the whole image or the rays ``pixels``
    [P,2] (as :func:`qr_cl.stages.select`) and its blend with ``features`` (as
    :func:`blend_forward`: the table's rows from 0, all N or a first row part): (the Selection,
    the image [P, cstride]). On CPU-shaped runtimes without a loop limit the K samplers blend each
    ray in the selection kernel right after selecting it (``BLEND_ROWS``: the same selection and
    image bytes, and the selection's entries are not read back); elsewhere the selection is made,
    then blended. Either way the Selection is complete when returned."""
    sel, kernel = pending_select(plan, sampler, k, pixels)
    if kernel is None:
        return sel, blend_forward(sel, features, channels, background, out)
    rt = plan.runtime
    vw, nv, cstride = channel_layout(channels, rt.narrow_rows)
    _check_part(sel, 0, features.shape[0], "features")
    image = _image(rt, sel.n_rays, features, cstride, out)
    kernel.run(defines={"VW": vw, "NV": nv, "BLEND_ROWS": 1, **row_defines(features)}, features=features,
               n_rows=features.shape[0], cstride=cstride, image=image,
               **_background(rt, background, channels, cstride, image))
    return sel, image


def blend_backward(sel: Selection, dimage: cla.Array, channels: int, out: cla.Array | None = None,
                   row0: int = 0, n_rows: int | None = None,
                   backward_index: BackwardIndex | None = None) -> cla.Array:
    """dF [R, cstride] with dF[g - row0] = sum over entries (p, j) with id[p,j] = g of w[p,j]
    dimage[p], for the Gaussians g of the rows [row0, row0 + R) (R = ``n_rows``; None: to N).

    dimage: float32 [P, cstride] device rows (the gradient of blend_forward's image); out: an
    optional float32 [R, cstride] device array to write into (else one from the runtime's pool).
    Each Gaussian's entries are summed by ray, then by position in the ray, so repeated calls
    return identical bytes, for any row part, on either kernel (:func:`scatters` says which): a
    scatter by OWNERS_PER_CORE work-items per compute unit, each owning a range of the part's
    Gaussians (no transpose), or a gather over :func:`qr_cl.stages.transpose.transpose`.
    ``backward_index``: the selection's :class:`BackwardIndex` (read and completed here; None:
    made for this call alone).
    """
    rt = sel.plan.runtime
    vw, nv, cstride = channel_layout(channels, rt.narrow_rows)
    n_rows = sel.n_gaussians - row0 if n_rows is None else n_rows
    _check_part(sel, row0, n_rows, "dF")
    _check_rows(dimage, sel.n_rays, cstride, "dimage")
    check_buffer(rt, 4 * n_rows * cstride, f"dF of {n_rows} Gaussians x {cstride} channels")
    dfeatures = device_empty(rt, (n_rows, cstride), np.float32) if out is None else out
    _check_rows(dfeatures, n_rows, cstride, "out")
    backward_index = BackwardIndex() if backward_index is None else backward_index
    if scatters(sel, backward_index):
        n_owners = OWNERS_PER_CORE * rt.device.max_compute_units
        key = (n_owners, row0, n_rows)
        if key not in backward_index.owners:
            backward_index.owners[key] = to_device(rt, owner_bounds(sel, n_owners, row0, row0 + n_rows), np.int32)
        bounds = backward_index.owners[key]
        rt.launch("blend_backward_scatter", bounds.size - 1, defines={"VW": vw, "NV": nv}, local_size=(1,),
                  n_owners=bounds.size - 1, bounds=bounds, n_rays=sel.n_rays,
                  offsets=sel.offsets, count=sel.count, n_entries=sel.ids.size, sel_ids=sel.ids,
                  sel_w=sel.weights, dimage=dimage, cstride=cstride, row0=row0,
                  touched=device_zeros(rt, max(n_rows, 1), np.uint8), dfeatures=dfeatures)
        return dfeatures
    t = backward_index.transpose(sel)
    args = dict(n=n_rows, order=backward_order(sel, t, row0, row0 + n_rows), n_chunks=t.chunks, cursor=t.cursor,
                t_ray=t.ray, t_w=t.weight, dimage=dimage, n_rays=sel.n_rays, cstride=cstride, row0=row0,
                dfeatures=dfeatures)
    windows = walk_windows(rt.loop_limit, longest_segment(t) if rt.loop_limit else 0, GATHER_LOOPS)
    if rt.gpu_shaped:
        defines, size, local = group_shape(rt, n_rows, cstride)
        kernel = "blend_backward_group"
    else:
        n_chunks = cstride // (vw * nv)
        size, local = work_groups(rt, n_rows, n_chunks)
        kernel, defines, size = "blend_backward", {"VW": vw, "NV": nv}, (size, n_chunks)
    for walk_from, walk_to in windows:
        rt.launch(kernel, size, defines=defines, local_size=local, **args, walk_from=walk_from, walk_to=walk_to)
    return dfeatures


def rows_to_half(rt: Runtime, rows: cla.Array, out: cla.Array) -> cla.Array:
    """``out`` (float16, the shape of ``rows``) = the float32 device array ``rows`` rounded to half,
    to nearest even (numpy's and torch's cast), by all the device's cores: a float16 table's
    gradient, summed in float32 by :func:`blend_backward`, in the table's dtype."""
    if rows.dtype != np.float32 or out.dtype != np.float16 or out.shape != rows.shape:
        raise ValueError(f"rows_to_half needs float32 rows and a float16 out of one shape, got {rows.dtype} "
                         f"{rows.shape} and {out.dtype} {out.shape}")
    if rows.size:
        rt.launch("rows_to_half", rows.size, defines={"VW": 1, "NV": 1}, n=rows.size, src=rows, dst=out)
    return out


def owner_bounds(sel: Selection, owners: int, g0: int = 0, g1: int | None = None) -> np.ndarray:
    """Cuts [owners + 1] int32 of the Gaussians g0..g1 (default 0..N) into ranges holding about
    equal numbers of ``sel``'s entries (the backward scatter's work-items; from a device histogram
    of the entries over OWNER_BINS bins of ids by transpose.cl's counting pass, so a cut falls on a
    bin's edge or on g0, g1). Always g0 first and g1 last."""
    rt, n = sel.plan.runtime, sel.n_gaussians
    g1 = n if g1 is None else g1
    shift = max(0, int(np.ceil(np.log2(max(n, 1) / OWNER_BINS))))
    bins = (max(n, 1) - 1 >> shift) + 1
    chunks = max(1, min(sel.n_rays, owners))
    hist = device_zeros(rt, chunks * bins, np.int32)
    if sel.n_rays:
        rt.launch("transpose_count", chunks, local_size=(1,), n_rays=sel.n_rays, rays_per=-(-sel.n_rays // chunks),
                  n_chunks=chunks, bin_shift=shift, offsets=sel.offsets, count=sel.count, n_entries=sel.ids.size,
                  n=n, sel_ids=sel.ids, hist=hist)
    cum = np.cumsum(hist.get().reshape(bins, chunks).sum(1))
    first = cum[(g0 >> shift) - 1] if g0 >> shift else 0          # the entries before g0's bin
    last = cum[max(g1 - 1, 0) >> shift]                               # ... up to g1's
    cuts = np.searchsorted(cum, first + (last - first) * np.arange(1, owners) / owners, side="right")
    return np.concatenate([[g0], np.clip(cuts << shift, g0, g1), [g1]]).astype(np.int32)


def scatters(sel: Selection, backward_index: BackwardIndex | None = None) -> bool:
    """Whether :func:`blend_backward` with ``backward_index`` scatters rather than gathers over the
    transpose: on CPU-shaped runtimes, for whole images (at least as many rays as Gaussians) and
    for pixel subsets whose transpose was not made ahead (:func:`prepare_backward`); GPU shapes
    always gather. On PoCL the
    scatter needs no transpose, so it measured faster for whole images and for subsets that would
    otherwise transpose on the spot; a transpose made ahead on another thread leaves the gather
    slightly faster (see qr-cl bench). A device with a loop limit gathers too: the scatter's few
    work-items each walk every ray."""
    rt = sel.plan.runtime
    if rt.gpu_shaped or rt.loop_limit is not None:
        return False
    return sel.n_rays >= sel.n_gaussians or backward_index is None or backward_index.transposed is None


def prepare_backward(sel: Selection) -> BackwardIndex:
    """The :class:`BackwardIndex` of ``sel`` with what :func:`blend_backward` will need made ahead
    (geometry only: the transpose, for GPU shapes and pixel subsets), e.g. on another thread while
    the network runs."""
    backward_index = BackwardIndex()
    if not scatters(sel, backward_index) or sel.n_rays < sel.n_gaussians:
        backward_index.transpose(sel)
    return backward_index


def _ray_pixels(sel: Selection) -> dict:
    """The ray -> pixel arguments (full, width, pixels) of blend.cl's geometry backward kernels."""
    rt = sel.plan.runtime
    pixels = np.zeros((1, 2), np.int32) if sel.pixels is None else sel.pixels
    return dict(full=int(sel.pixels is None), width=sel.plan.width, pixels=to_device(rt, pixels, np.int32))


def weight_grads(sel: Selection, features: cla.Array, dimage: cla.Array, channels: int, row0: int = 0,
                 out: cla.Array | None = None) -> cla.Array:
    """dL/dw per selection entry [E] float32 (the layout of ``sel.ids``): dimage[p] . F[id] of the
    entries whose Gaussian is among the rows [row0, row0 + R) that ``features`` hold (float32 or
    float16 [R, cstride] device rows, the whole table or a row part), written into ``out`` (else a
    pooled array); the other entries of ``out`` are left as they are, for the other parts.
    dimage: float32 [P, cstride] device rows of dL/dimage. The input of :func:`blend_backward_alpha`."""
    rt = sel.plan.runtime
    vw, _, cstride = channel_layout(channels, rt.narrow_rows)
    _check_part(sel, row0, features.shape[0], "features")
    _check_rows(features, features.shape[0], cstride, "features", half=True)
    _check_rows(dimage, sel.n_rays, cstride, "dimage")
    d_w = device_empty(rt, sel.ids.shape, np.float32) if out is None else out
    _check_entries(d_w, sel, "out")
    if sel.n_rays == 0:
        return d_w
    for walk_from, walk_to in walk_windows(rt.loop_limit, longest_entries(sel) if rt.loop_limit else 0,
                                           cstride // vw + 2):
        rt.launch("weight_grads", sel.n_rays, defines={"VW": vw, "NV": 1, **row_defines(features)},
                  n_rays=sel.n_rays, offsets=sel.offsets, count=sel.count, n_entries=sel.ids.size, sel_ids=sel.ids,
                  features=features, row0=row0, n_rows=features.shape[0], dimage=dimage, cstride=cstride, d_w=d_w,
                  walk_from=walk_from, walk_to=walk_to)
    return d_w


def blend_backward_alpha(sel: Selection, d_w: cla.Array, d_trem: np.ndarray | None = None) -> cla.Array:
    """dL/dalpha per selection entry [E] float32 (the layout of ``sel.ids``), computed in place in
    ``d_w``, which holds dL/dw of every entry on entry (:func:`weight_grads` of every row part of
    the table): the blend's backward w.r.t. the alphas of the selected Gaussians, recomputed from
    the plan's splats (see ``blend_backward_alpha`` in kernels/blend.cl for the formulas of volume
    and of the normalized K samplers).

    d_trem: [P] dL/d(final transmittance) of each ray (volume only: the background weight and
    1 - alpha; None = 0; ignored by the K samplers, whose background weight does not depend on the
    alphas).
    """
    rt = sel.plan.runtime
    _check_entries(d_w, sel, "d_w")
    if sel.n_rays == 0:
        return d_w
    d_trem = np.zeros(sel.n_rays, np.float32) if d_trem is None else np.asarray(d_trem, np.float32)
    # blend_backward_alpha reads no feature rows; blend.cl is built with some row vector width all the same
    rt.launch("blend_backward_alpha", sel.n_rays, defines={"VW": 1, "NV": 1}, n_rays=sel.n_rays,
              **_ray_pixels(sel), offsets=sel.offsets, count=sel.count, n_entries=sel.ids.size,
              n=sel.n_gaussians, sel_ids=sel.ids, sel_w=sel.weights, splats=sel.plan.splats,
              normalized=int(sel.sampler != "volume"), d_trem=to_device(rt, d_trem, np.float32), d_alpha=d_w)
    return d_w


def splat_backward(sel: Selection, d_alpha: cla.Array,
                   backward_index: BackwardIndex | None = None) -> cla.Array:
    """dL/dsplat [N, 8] float32 (d mean2d in px, d conic and d opacity in their slots of
    :data:`~qr_cl.runtime.SPLAT`, and in its ``absgrad`` slots the sums over the entries of
    |d mean2d x| and |d mean2d y|, gsplat's absgrad) from
    dL/dalpha per selection entry (:func:`blend_backward_alpha`), summed per Gaussian over the
    selection's transpose in a fixed order (bitwise reproducible). Entries whose alpha was
    clamped to ALPHA_MAX contribute nothing. ``backward_index``: as :func:`blend_backward`'s."""
    rt = sel.plan.runtime
    t = (BackwardIndex() if backward_index is None else backward_index).transpose(sel)
    d_splats = device_empty(rt, (sel.n_gaussians, SPLAT_FLOATS), np.float32)
    # splat_backward reads no feature rows; blend.cl is built with some row vector width all the same
    for walk_from, walk_to in walk_windows(rt.loop_limit, longest_segment(t) if rt.loop_limit else 0, SPLAT_LOOPS):
        rt.launch("splat_backward", sel.n_gaussians, defines={"VW": 1, "NV": 1}, n=sel.n_gaussians,
                  n_chunks=t.chunks, cursor=t.cursor, t_ray=t.ray, t_entry=t.entry, d_alpha=d_alpha,
                  splats=sel.plan.splats, **_ray_pixels(sel), d_splats=d_splats, walk_from=walk_from,
                  walk_to=walk_to)
    return d_splats
