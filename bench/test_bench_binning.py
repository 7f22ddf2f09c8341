"""Binning building blocks: pyopencl's scan and RadixSort vs numpy on the host (CPU device).

This measurement is why ``qr_cl.stages.sort_pairs`` sorts on the host when the device is
the CPU: there pyopencl's RadixSort is slower than numpy's stable argsort, copies included, and
torch's stable sort (a radix sort of int64 keys, one thread) is faster again, so ``sort_pairs``
uses it (``test_sort_pairs_host``). pyopencl's scan is kept: it runs on every device.

    pytest bench/test_bench_binning.py --benchmark-only
"""
import numpy as np
import pyopencl.array as cla
import pytest

from benchutil import run
from qr_cl.runtime import exclusive_scan, runtime, to_device
from qr_cl.scene import orbit_cameras
from qr_cl.stages import project, radix_sorter, tile_grid


@pytest.fixture(scope="module")
def keys(fox_or_procedural):
    """Device arrays (tiles touched [N], unsorted keys [M], values [M]) and the key bit count."""
    g, w, h = fox_or_procedural
    rt = runtime()
    cam = orbit_cameras(g.means, 8, w, h)[1]
    dev = [to_device(rt, a) for a in (g.means, g.quats, g.scales, g.opacities)]
    splats, _, footprints, touched, _ = project(rt, *dev, cam.viewmat, cam.K, w, h, 0.01, 1e10)
    offsets = exclusive_scan(rt, touched, cla.empty_like(touched))
    m = int(touched.get().sum())
    keys, values = cla.empty(rt.queue, m, np.uint64), cla.empty(rt.queue, m, np.int32)
    tiles_x, tiles_y = tile_grid(w, h)
    rt.launch("emit_keys", len(g), n=len(g), footprints=footprints, offsets=offsets, splats=splats,
              tiles_x=tiles_x, keys=keys, values=values)
    n_tiles = tiles_x * tiles_y
    return touched, keys, values, 32 + int(n_tiles - 1).bit_length()


def test_scan_pyopencl(benchmark, keys, bench_full):
    rt, (touched, *_) = runtime(), keys
    out = cla.empty_like(touched)
    run(benchmark, lambda: (exclusive_scan(rt, touched, out), rt.queue.finish()), bench_full)
    np.testing.assert_array_equal(out.get(), np.cumsum(touched.get()) - touched.get())


def test_scan_numpy_host(benchmark, keys, bench_full):
    rt, (touched, *_) = runtime(), keys
    run(benchmark, lambda: cla.to_device(rt.queue, np.cumsum(touched.get()) - touched.get()).finish(),
        bench_full)


def test_sort_pyopencl_radix(benchmark, keys, bench_full):
    rt, (_, k, v, bits) = runtime(), keys
    sorter = radix_sorter(rt.context)

    def sort():
        out = sorter(k, v, key_bits=bits)
        rt.queue.finish()  # the timed call includes the device work, not just the enqueue
        return out
    (sk, sv), _ = run(benchmark, sort, bench_full)
    order = np.argsort(k.get(), kind="stable")
    np.testing.assert_array_equal(sk.get(), k.get()[order])
    np.testing.assert_array_equal(sv.get(), v.get()[order])


def test_sort_numpy_host(benchmark, keys, bench_full):
    rt, (_, k, v, _) = runtime(), keys

    def sort():
        order = np.argsort(k.get(), kind="stable")
        out = cla.to_device(rt.queue, k.get()[order]), cla.to_device(rt.queue, v.get()[order])
        rt.queue.finish()
        return out
    run(benchmark, sort, bench_full)


def test_sort_pairs_host(benchmark, keys, bench_full):
    """qr-cl's CPU path (torch's stable sort into pooled host arrays), equal to numpy's stable order."""
    from qr_cl.stages import sort_pairs
    rt, (_, k, v, bits) = runtime(), keys
    sk, sv = run(benchmark, lambda: sort_pairs(rt, k, v, bits), bench_full)
    order = np.argsort(k.get(), kind="stable")
    np.testing.assert_array_equal(sk.get(), k.get()[order])
    np.testing.assert_array_equal(sv.get(), v.get()[order])
