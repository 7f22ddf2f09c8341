"""Selection: which Gaussians each ray blends, with what weight (select.cl), per sampler.

A Selection depends only on geometry, camera, sampler and K, never on features: it is computed
once per view and shared by the blend forward and backward (:mod:`qr_cl.blend`).

Samplers:
    ``volume``   every Gaussian V-Render blends (alpha >= 1/255, until T would drop to <= 1e-4),
                 w_i = T_i alpha'_i; background weight = the final T.
    ``quantile`` Algorithm 1 of the paper (K quantile Gaussians), w = T^Q alpha' / (1 - T^Q).
    ``topk``     the K largest V-Render weights, re-composited in depth order among the selected,
                 normalized by 1 / (1 - T) as Q-Render.
For quantile and topk the normalized weights sum to 1, so the background only shows through rays
that selected nothing (background weight 1 there, 0 elsewhere).
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
import pyopencl.array as cla

from .raster import TILE, RasterPlan, exclusive_scan

SELECT_SAMPLERS = ("volume", "quantile", "topk")


@dataclass
class Selection:
    """Per-ray (Gaussian id, weight) lists on the device.

    Rays: the whole image (``pixels is None``, ray p = y * width + x) or a pixel subset
    (``pixels`` [P,2] int32 (x, y), ray p = row p). Entries of ray p are
    ``[offsets[p], offsets[p] + count[p])`` of ``ids`` / ``weights`` (int32 / float32; quantile
    and topk: dense rows of K at p * K, padded with -1 / 0). Per ray (float32 [P]): ``t_walk`` the
    transmittance where the ray's walk stopped, ``t_sel`` the transmittance among the selected
    Gaussians before normalization (T^Q; the final T for volume), ``t_rem`` the background weight.
    ``k`` is K (0 for volume); ``n_gaussians`` is N of the plan.
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
    transposed: tuple | None = field(default=None, repr=False)

    @property
    def n_rays(self) -> int:
        return self.plan.width * self.plan.height if self.pixels is None else len(self.pixels)

    @property
    def n_gaussians(self) -> int:
        return self.plan.splats.shape[0]

    @property
    def nbytes(self) -> int:
        """Device bytes held by the selection (and its cached transpose)."""
        arrays = [self.ids, self.weights, self.offsets, self.count, self.t_walk, self.t_sel, self.t_rem]
        arrays += [a for a in self.transposed or () if isinstance(a, cla.Array)]
        return sum(a.nbytes for a in arrays)

    def launch(self) -> tuple[int, int]:
        """(global size of a per-ray kernel, full-image flag)."""
        if self.pixels is None:
            return self.plan.tiles_x * self.plan.tiles_y * TILE * TILE, 1
        return len(self.pixels), 0

    def host(self) -> dict[str, np.ndarray]:
        """Host copies as dense arrays: ids [P,L] (-1 padded) and weights [P,L] (0 padded) with L the
        longest list, count, t_walk, t_sel, t_rem [P]."""
        n = self.n_rays
        count, offsets = self.count.get()[:n], self.offsets.get()[:n]
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


def select(plan: RasterPlan, sampler: str = "quantile", k: int = 40, pixels=None) -> Selection:
    """Run the selection kernel of ``sampler`` ("volume", "quantile" or "topk") with K = ``k``
    (ignored by volume) for the whole image or the rays ``pixels`` [P,2] (x, y) in px.

    Cost is proportional to the number of rays (and their tile lists), not to width * height.
    """
    if sampler not in SELECT_SAMPLERS:
        raise ValueError(f"sampler={sampler!r}: selection samplers are {SELECT_SAMPLERS}")
    if sampler != "volume" and (isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1):
        raise ValueError(f"K must be an integer >= 1, got {k!r}")
    k = int(k) if sampler != "volume" else 0
    rt = plan.runtime
    q = rt.queue
    if pixels is not None:
        pixels = check_pixels(pixels, plan.width, plan.height)
    n_rays = plan.width * plan.height if pixels is None else len(pixels)
    pix_dev = cla.to_device(q, pixels if pixels is not None and len(pixels) else np.zeros((1, 2), np.int32))
    per_ray = [cla.empty(q, max(n_rays, 1), dt) for dt in (np.int32, np.float32, np.float32, np.float32)]
    count, t_walk, t_sel, t_rem = per_ray
    sel = Selection(plan, sampler, k, pixels, cla.empty(q, 1, np.int32), cla.empty(q, 1, np.float32),
                    cla.zeros(q, max(n_rays, 1), np.int32), count, t_walk, t_sel, t_rem)
    if n_rays == 0:
        return sel
    size, full = sel.launch()
    ray_args = (plan.ranges.data, plan.ids.data, plan.splats.data, pix_dev.data, np.int32(full),
                np.int32(plan.width), np.int32(plan.height), np.int32(plan.tiles_x))
    if sampler == "volume":
        rt.kernel("select.cl", "volume_count")(q, (size,), None, *ray_args, count.data, t_walk.data)
        exclusive_scan(rt.context)(count, sel.offsets)
        total = int(sel.offsets[n_rays - 1:n_rays].get()[0] + count[n_rays - 1:n_rays].get()[0])
        sel.ids = cla.empty(q, max(total, 1), np.int32)
        sel.weights = cla.empty(q, max(total, 1), np.float32)
        rt.kernel("select.cl", "volume_fill")(q, (size,), None, *ray_args, sel.offsets.data,
                                             sel.ids.data, sel.weights.data, t_sel.data, t_rem.data)
    else:
        sel.ids = cla.empty(q, n_rays * k, np.int32)
        sel.weights = cla.empty(q, n_rays * k, np.float32)
        sel.offsets = cla.arange(q, 0, n_rays * k, k, dtype=np.int32)
        rt.kernel("select.cl", f"select_{sampler}")(
            q, (size,), None, *ray_args, np.int32(k), sel.ids.data, sel.weights.data, count.data,
            t_walk.data, t_sel.data, t_rem.data)
    return sel


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
        plan = sel.plan
        return sel.nbytes + plan.splats.nbytes + plan.radii.nbytes + plan.ranges.nbytes + plan.ids.nbytes

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


def transmittance_profile(selection: Selection, ray: int) -> tuple[np.ndarray, np.ndarray]:
    """Transmittance along ray ``ray`` as its sampler sees it: (depths [n] of the selected
    Gaussians in camera z, T [n+1] before the first and after each selected Gaussian).

    volume: T_i of the full walk; quantile/topk: T^Q among the selected (un-normalized). This is
    what the paper's Fig. 3 plots (see :func:`plot_transmittance_profiles`).
    """
    h = selection.host()
    n = int(h["count"][ray])
    ids, w = h["ids"][ray, :n], h["weights"][ray, :n].astype(np.float64)
    scale = 1.0 if selection.sampler == "volume" else 1.0 - float(h["t_sel"][ray])
    t = 1.0 - np.concatenate([[0.0], np.cumsum(w * scale)])
    depths = selection.plan.splats.get().reshape(-1, 8)[ids, 6] if n else np.zeros(0, np.float32)
    return depths, t


def plot_transmittance_profiles(profiles: dict[str, tuple[np.ndarray, np.ndarray]], path: str,
                                title: str = "") -> None:
    """Step plot of T against depth for each sampler of ``profiles`` (name -> (depths, T) from
    :func:`transmittance_profile`), saved to ``path`` (any matplotlib format)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for name, (depths, t) in profiles.items():
        if len(depths):
            ax.step(np.concatenate([[depths[0]], depths]), t, where="post", marker=".", label=name)
    ax.set_xlabel("depth (camera z)")
    ax.set_ylabel("transmittance T")
    ax.set_ylim(-0.02, 1.02)
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
