"""Binning building blocks: pyopencl's scan and RadixSort vs numpy on the host (CPU device).

This measurement is why ``raster.sort_pairs`` sorts with numpy when the device is the CPU:
on the fox scene at 640x480 (105k keys) pyopencl's RadixSort took ~17 ms and numpy's stable
argsort, copies included, ~4.6 ms. pyopencl's scan (~0.27 ms, numpy 0.21 ms) is kept: it runs
on every device.

    pytest bench/test_bench_binning.py --benchmark-only
"""
import numpy as np
import pyopencl.array as cla
import pytest

from benchutil import run
from qr_cl import raster
from qr_cl.camera import orbit_cameras
from qr_cl.device import runtime


@pytest.fixture(scope="module")
def keys(fox_or_procedural):
    """Device arrays (tiles touched [N], unsorted keys [M], values [M]) and the key bit count."""
    g, w, h = fox_or_procedural
    rt = runtime()
    cam = orbit_cameras(g.means, 8, w, h)[1]
    dev = [raster.to_device(rt, a) for a in (g.means, g.quats, g.scales, g.opacities)]
    splats, _, rects, touched = raster.project(rt, *dev, cam.viewmat, cam.K, w, h, 0.01, 1e10)
    offsets = cla.empty_like(touched)
    raster.exclusive_scan(rt.context)(touched, offsets)
    m = int(touched.get().sum())
    keys, values = cla.empty(rt.queue, m, np.uint64), cla.empty(rt.queue, m, np.int32)
    tiles_x = (w + 15) // 16
    rt.kernel("binning.cl", "emit_keys")(rt.queue, (len(g),), None, np.int32(len(g)), rects.data,
                                         offsets.data, splats.data, np.int32(tiles_x), keys.data, values.data)
    n_tiles = tiles_x * ((h + 15) // 16)
    return touched, keys, values, 32 + int(n_tiles - 1).bit_length()


def test_scan_pyopencl(benchmark, keys, bench_full):
    rt, (touched, *_) = runtime(), keys
    out = cla.empty_like(touched)
    run(benchmark, lambda: (raster.exclusive_scan(rt.context)(touched, out), rt.queue.finish()), bench_full)
    np.testing.assert_array_equal(out.get(), np.cumsum(touched.get()) - touched.get())


def test_scan_numpy_host(benchmark, keys, bench_full):
    rt, (touched, *_) = runtime(), keys
    run(benchmark, lambda: cla.to_device(rt.queue, np.cumsum(touched.get()) - touched.get()).finish(),
        bench_full)


def test_sort_pyopencl_radix(benchmark, keys, bench_full):
    rt, (_, k, v, bits) = runtime(), keys
    sorter = raster._radix_sort(rt.context)

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
