"""Selection and blend time per sampler next to the fused V-Render, in the same run.

    pytest bench/test_bench_samplers.py --benchmark-only

Full mode: the fox scene (50k Gaussians, orbit camera 1 of 8) at 640x480, C = 512, K in {10, 40};
smoke mode (default run): a tiny procedural scene at 64x48. Every timed call ends with
``queue.finish()``. The blend writes into a reused device buffer (a fresh 600 MB buffer would
time its page faults) and leaves the image on the device; the fused V-Render is timed as
rasterize() calls it (its image lands in a host array through a zero-copy buffer).
"""
import numpy as np
import pyopencl.array as cla
import pytest

from benchutil import run
from qr_cl.render import rasterize_plan
from qr_cl.runtime import channel_layout, padded_rows, to_device
from qr_cl.scene import orbit_cameras
from qr_cl.stages import blend_backward, blend_forward, render_fused, select

C = 512
CASES = [("volume", 0), ("quantile", 10), ("quantile", 40), ("topk", 10), ("topk", 40)]


@pytest.fixture(scope="module")
def setup(fox_or_procedural):
    g, w, h = fox_or_procedural
    cam = orbit_cameras(g.means, 8, w, h)[1]
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, w, h)
    feats = np.random.default_rng(0).standard_normal((len(g), C)).astype(np.float32)
    q = plan.runtime.queue
    out = cla.empty(q, (w * h, channel_layout(C)[2]), np.float32)
    return plan, to_device(plan.runtime, padded_rows(feats, channel_layout(C)[2])), out


def _label(sampler: str, k: int) -> str:
    return sampler if sampler == "volume" else f"{sampler} K={k}"


def test_fused_vrender(benchmark, setup, bench_full):
    """The fused V-Render (no stored selection) as rasterize() calls it, image written to the host.
    Its blend of the volume selection is checked against it."""
    plan, features, _ = setup
    benchmark.group = "fused V-Render vs select + blend"
    image, _, _ = run(benchmark, lambda: render_fused(plan, features, C), bench_full)
    blended = blend_forward(select(plan, "volume", 1), features, C).get()
    np.testing.assert_allclose(image.reshape(blended.shape), blended, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("sampler,k", CASES)
def test_select(benchmark, setup, bench_full, sampler, k):
    plan, _, _ = setup

    def step():
        sel = select(plan, sampler, k or 1)
        plan.runtime.queue.finish()
        return sel

    benchmark.group = "fused V-Render vs select + blend"
    benchmark.name = f"select {_label(sampler, k)}"
    sel = run(benchmark, step, bench_full)
    counts = sel.count.get()
    benchmark.extra_info["mean_entries_per_ray"] = float(counts.mean())
    assert counts.max() > 0


@pytest.mark.parametrize("sampler,k", CASES)
def test_blend(benchmark, setup, bench_full, sampler, k):
    plan, features, out = setup
    sel = select(plan, sampler, k or 1)

    def step():
        blend_forward(sel, features, C, out=out)
        plan.runtime.queue.finish()

    benchmark.group = "fused V-Render vs select + blend"
    benchmark.name = f"blend {_label(sampler, k)}"
    run(benchmark, step, bench_full)


@pytest.mark.parametrize("sampler,k", CASES)
def test_backward(benchmark, setup, bench_full, sampler, k):
    """dF from dImage (on GPU-shaped runtimes including the transpose, rebuilt every round)."""
    plan, features, out = setup
    sel = select(plan, sampler, k or 1)

    def step():
        d = blend_backward(sel, out, C)          # without views: its transpose made anew
        plan.runtime.queue.finish()
        return d

    benchmark.group = "backward"
    benchmark.name = f"backward {_label(sampler, k)}"
    d = run(benchmark, step, bench_full)
    assert d.shape == (sel.n_gaussians, channel_layout(C)[2])


@pytest.mark.parametrize("k", [5, 10, 20, 40])
def test_quantile_error_vs_volume(benchmark, setup, bench_full, k):
    """Q-Render select + blend, with its mean absolute feature error against V-Render over the rays
    V-Render hits (V-Render divided by its opacity 1 - T, as Q-Render's weights sum to 1; App. C),
    recorded in extra_info for the 512-D features of the setup (unit-normalized rows here)."""
    plan, features, out = setup
    unit = features.get()
    unit /= np.maximum(np.linalg.norm(unit, axis=1, keepdims=True), 1e-12)
    unit_dev = to_device(plan.runtime, unit)
    vol = select(plan, "volume", 1)
    hit = vol.count.get() > 0
    v_img = blend_forward(vol, unit_dev, C).get()[hit] / (1 - vol.t_walk.get()[hit, None])

    def step():
        blend_forward(select(plan, "quantile", k), unit_dev, C, out=out)
        plan.runtime.queue.finish()

    benchmark.group = "Q-Render select + blend, error vs V-Render"
    benchmark.name = f"quantile K={k}"
    run(benchmark, step, bench_full, rounds=3)
    error = float(np.abs(out.get()[hit] - v_img).mean())
    benchmark.extra_info["mean_abs_feature_error_vs_volume"] = error
    print(f"\nK={k}: mean |Q - V/(1-T)| = {error:.5f} over {hit.sum()} rays")
    assert error < 0.1
