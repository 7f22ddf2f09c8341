"""A wrong answer from a driver never becomes a crash: counts no kernel wrote are zero, and the
kernels that consume a Selection bound its counts by its buffers and its ids by the Gaussians.

On Mesa 22's rusticl a top-K selection cut short left counts unwritten in a pooled buffer that
held a float's bits (1.0 = 1065353216 entries), and transpose_count walked into unmapped memory.
Here a child process corrupts a selection that way (and with ids outside the scene) and runs every
consumer on both launch shapes; a crash is the child's death, so it runs apart from pytest.

Run as a script (``python tests/drivers/test_driver_faults.py``) this file is the child.
"""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

N, W, H, C = 300, 48, 32, 16


def scene():
    rng = np.random.default_rng(3)
    z = rng.uniform(2, 5, N)
    means = np.c_[rng.uniform(-0.7, 0.7, N) * z, rng.uniform(-0.5, 0.5, N) * z, z].astype(np.float32)
    quats = rng.normal(size=(N, 4)).astype(np.float32)
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = np.exp(rng.uniform(-3, -0.7, (N, 3))).astype(np.float32)
    opacities = rng.uniform(0.1, 0.9, N).astype(np.float32)
    return means, quats, scales, opacities


def child() -> None:
    from qr_cl.render import rasterize_plan
    from qr_cl.runtime import channel_layout, to_device
    from qr_cl.scene import look_at
    from qr_cl.stages import blend as blend_module
    from qr_cl.stages import (blend_backward, blend_backward_alpha, blend_forward, scatters, select, splat_backward,
                              weight_grads)

    cam = look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 30.0, 30.0, W, H)
    plan = rasterize_plan(*scene(), cam.viewmat, cam.K, W, H)
    rt = plan.runtime
    cstride = channel_layout(C, rt.gpu_shaped)[2]
    rows = np.random.default_rng(0).normal(size=(N, cstride))
    features, part = to_device(rt, rows), to_device(rt, rows[N // 2:])      # the table, its second row part
    dimage = to_device(rt, np.ones((W * H, cstride)))
    for sampler in ("topk", "volume"):
        sel = select(plan, sampler, 6)
        count, ids = sel.count.get(), sel.ids.get()
        count[::7] = 1065353216                         # the bits of 1.0f: a pooled buffer's old floats
        count[3::11] = -40
        ids[::5] = [-3, N, 2 ** 31 - 1, -(2 ** 31)] * (len(ids[::5]) // 4) + [N + 7] * (len(ids[::5]) % 4)
        sel.count.set(count)
        sel.ids.set(ids)
        blend_forward(sel, features, C).get()
        blend_forward(sel, part, C, row0=N // 2).get()
        for scatter in (True, False):                   # both backward kernels (the gather transposes)
            blend_module.scatters = (lambda s, backward_index=None, v=scatter: v)
            blend_backward(sel, dimage, C).get()
            blend_backward(sel, dimage, C, row0=N // 2).get()
        blend_module.scatters = scatters
        d_w = weight_grads(sel, features, dimage, C)
        d_alpha = blend_backward_alpha(sel, weight_grads(sel, part, dimage, C, row0=N // 2, out=d_w))
        splat_backward(sel, d_alpha).get()
        print(f"{sampler}: survived")


@pytest.mark.parametrize("shape", ["cpu", "gpu"])
def test_corrupt_counts_and_ids_are_bounded_not_followed(shape):
    env = {**os.environ, "QR_CL_LAUNCH": shape}
    run = subprocess.run([sys.executable, __file__], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, f"the child died ({run.returncode}):\n{run.stdout}\n{run.stderr[-3000:]}"
    assert run.stdout.split() == ["topk:", "survived", "volume:", "survived"]


def test_counts_no_kernel_wrote_are_zero(random_scene, monkeypatch):
    """A selection kernel that never ran (or ended before writing) leaves rays that select nothing."""
    from qr_cl.render import rasterize_plan
    from qr_cl.runtime import Runtime, device_empty
    from qr_cl.stages import select
    m, q, s, o, v, K, w, h = random_scene
    plan = rasterize_plan(m, q, s, o, v, K, w, h)
    garbage = device_empty(plan.runtime, w * h, np.int32)
    garbage.fill(1065353216)
    del garbage                                          # back to the pool, bits and all
    launch = Runtime.launch
    monkeypatch.setattr(Runtime, "launch", lambda self, name, *a, **k: None if name.startswith("select_")
                        else launch(self, name, *a, **k))
    sel = select(plan, "topk", 4)
    host = sel.host()
    assert np.all(host["count"] == 0) and np.all(host["t_rem"] == 0)


if __name__ == "__main__":
    child()
