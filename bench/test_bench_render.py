"""End-to-end render time: the OpenCL pipeline vs the numpy reference, in the same run.

    pytest bench/test_bench_render.py --benchmark-only

Full mode: the fox scene (50k Gaussians, orbit camera) at 640x480, RGB from SH and 512-D
features; smoke mode: a tiny procedural scene.
"""
import numpy as np
import pytest

import qr_cl
from benchutil import run
from qr_cl.scene import orbit_cameras
from qr_cl.stages import sh_ref, vrender_ref


@pytest.fixture(scope="module")
def setup(fox_or_procedural):
    g, w, h = fox_or_procedural
    cam = orbit_cameras(g.means, 8, w, h)[1]
    feats = {"rgb": None, "512": np.random.default_rng(0).random((len(g), 512), dtype=np.float32)}
    return g, cam, feats


@pytest.mark.parametrize("what", ["rgb", "512"])
def test_render_opencl(benchmark, setup, bench_full, what):
    g, cam, feats = setup
    benchmark.group = f"render {what}"
    f, deg = (g.sh, g.sh_degree) if what == "rgb" else (feats[what], None)
    img, alpha, _ = run(benchmark, lambda: qr_cl.rasterize(g.means, g.quats, g.scales, g.opacities, f,
                                                           cam.viewmat, cam.K, cam.width, cam.height,
                                                           sh_degree=deg), bench_full)
    assert img.shape[-1] == (3 if what == "rgb" else 512) and float(alpha.max()) > 0


@pytest.mark.parametrize("what", ["rgb", "512"])
def test_render_numpy_reference(benchmark, setup, bench_full, what):
    g, cam, feats = setup
    benchmark.group = f"render {what}"
    f = sh_ref.sh_to_rgb(g.means, g.sh, cam.position) if what == "rgb" else feats[what]
    img, alpha, *_ = run(benchmark, lambda: vrender_ref.render(g.means, g.quats, g.scales, g.opacities, f,
                                                       cam.viewmat, cam.K, cam.width, cam.height),
                         bench_full, rounds=1)
    assert float(alpha.max()) > 0
