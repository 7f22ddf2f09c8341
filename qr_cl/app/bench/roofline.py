"""This device's limits, measured by small kernels: streaming bandwidth, FMA rate, and the bare
gather-blend of P rays x K entries x C channels with spatially coherent ids."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla

from ...runtime import Runtime, channel_layout, streamed
from ...stages import work_groups
from ..timing import measure

FMA_ITERS = 4096


def stream_bandwidth(rt: Runtime, mib: int = 256, rounds: int = 5) -> float:
    """Triad bandwidth in bytes/s over three arrays of ``mib`` MiB each."""
    n = mib * 2 ** 20 // 64
    a, b, c = (cla.zeros(rt.queue, n * 16, np.float32) for _ in range(3))

    def run():
        rt.launch("triad", n, n=n, a=a, b=b, c=c, s=0.5)
        rt.queue.finish()
    return 3 * n * 64 / measure(run, rounds)["min_s"]


def fma_rate(rt: Runtime, work_items: int = 4096, rounds: int = 5) -> float:
    """Peak float32 rate in flop/s (an FMA counts as 2) with explicit float16 vectors."""
    out = cla.empty(rt.queue, work_items, np.float32)

    def run():
        rt.launch("fma_peak", work_items, defines={"ITERS": FMA_ITERS}, n=work_items, out=out, x=1.0)
        rt.queue.finish()
    return work_items * 8 * 16 * 2 * FMA_ITERS / measure(run, rounds)["min_s"]


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
    vw, nv, cstride = channel_layout(channels, rt.gpu_shaped)
    offsets, count, ids, weights = coherent_selection(rt, rays, k, n_rows)
    features = cla.zeros(rt.queue, (n_rows, cstride), np.float32)
    image = cla.empty(rt.queue, (rays, cstride), np.float32)
    unused = cla.zeros(rt.queue, max(rays, cstride), np.float32)   # background and t_rem (no bg)

    n_chunks = cstride // (vw * nv)
    size, local = work_groups(rt, rays, n_chunks)

    def run():
        rt.launch("blend", (size, n_chunks), defines={"VW": vw, "NV": nv}, local_size=local,
                  offsets=offsets, count=count, n_entries=ids.size, sel_ids=ids, sel_w=weights,
                  features=features, row0=0, n_rows=n_rows, cstride=cstride, full=0, n_rays=rays, width=0,
                  height=0, tiles_x=1, background=unused, t_rem=unused, use_bg=0, accumulate=0,
                  stream=streamed(image.nbytes), image=image)
        rt.queue.finish()
    return measure(run, rounds)["min_s"]
