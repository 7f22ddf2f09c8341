"""This device's limits, measured by small kernels: streaming bandwidth, FMA rate, and the bare
gather-blend of P rays x K entries x C channels with spatially coherent ids."""
from __future__ import annotations

import time

import numpy as np
import pyopencl.array as cla

from .device import Runtime
from .vrender import channel_layout

FMA_ITERS = 4096


def best_time(fn, rounds: int = 5) -> float:
    """Minimum wall time in seconds of ``fn()`` over ``rounds`` (after one warm-up call)."""
    fn()
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def stream_bandwidth(rt: Runtime, mib: int = 256, rounds: int = 5) -> float:
    """Triad bandwidth in bytes/s over three arrays of ``mib`` MiB each."""
    n = mib * 2 ** 20 // 64
    a, b, c = (cla.zeros(rt.queue, n * 16, np.float32) for _ in range(3))
    kernel = rt.kernel("roofline.cl", "triad")

    def run():
        kernel(rt.queue, (n,), None, a.data, b.data, c.data, np.float32(0.5))
        rt.queue.finish()
    return 3 * n * 64 / best_time(run, rounds)


def fma_rate(rt: Runtime, work_items: int = 4096, rounds: int = 5) -> float:
    """Peak float32 rate in flop/s (an FMA counts as 2) with explicit float16 vectors."""
    out = cla.empty(rt.queue, work_items, np.float32)
    kernel = rt.kernel("roofline.cl", "fma_peak", ITERS=FMA_ITERS)

    def run():
        kernel(rt.queue, (work_items,), None, out.data, np.float32(1.0))
        rt.queue.finish()
    return work_items * 8 * 16 * 2 * FMA_ITERS / best_time(run, rounds)


def coherent_selection(rt: Runtime, rays: int, k: int, n_rows: int, seed: int = 0):
    """Device arrays (offsets, count, ids, weights) of ``rays`` dense rows of ``k`` entries whose
    ids are spatially coherent: ray p draws from a window of 4k rows around p * n_rows / rays."""
    rng = np.random.default_rng(seed)
    centre = (np.arange(rays) * (n_rows / max(rays, 1))).astype(np.int64)
    ids = np.clip(centre[:, None] + rng.integers(-2 * k, 2 * k, (rays, k)), 0, n_rows - 1)
    weights = rng.random((rays, k), dtype=np.float32) / k
    host = [(np.arange(rays) * k, np.int32), (np.full(rays, k), np.int32), (ids.ravel(), np.int32),
            (weights.ravel(), np.float32)]
    return tuple(cla.to_device(rt.queue, np.ascontiguousarray(a, t)) for a, t in host)


def bare_gather_blend(rt: Runtime, rays: int, k: int, channels: int, n_rows: int = 200_000,
                      rounds: int = 3) -> float:
    """Seconds of the blend kernel alone on a coherent [rays, k] selection of [n_rows, C] rows."""
    vw, nv, cstride = channel_layout(channels)
    offsets, count, ids, weights = coherent_selection(rt, rays, k, n_rows)
    features = cla.zeros(rt.queue, (n_rows, cstride), np.float32)
    image = cla.empty(rt.queue, (rays, cstride), np.float32)
    zeros = cla.zeros(rt.queue, max(rays, cstride), np.float32)
    kernel = rt.kernel("blend.cl", "blend", VW=vw, NV=nv)

    def run():
        kernel(rt.queue, (rays, cstride // (vw * nv)), None, offsets.data, count.data, ids.data,
               weights.data, features.data, np.int32(cstride), np.int32(0), np.int32(0), np.int32(0),
               np.int32(1), zeros.data, zeros.data, np.int32(0), image.data)
        rt.queue.finish()
    return best_time(run, rounds)
