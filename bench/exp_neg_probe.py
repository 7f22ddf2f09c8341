"""Probe: qr-cl's exp_neg (kernels/common.h) against the implementation's library exp.

1. Exactness: e^-x of 1M arguments by exp_neg in float16 vectors and in scalars (equal bits?),
   its error in ulp against float64, and how many library exps differ between vectors and scalars.
2. Throughput: 256 exps per lane of 1M lanes in float16 vectors: exp_neg with its rounding by
   1.5 * 2^23, the same with rint, and the library exp (CPU time of the process).
3. In the walks: Q-Render K=40's and V-Render's selection and the fused V-Render of 3 channels on
   the dense 300k room and the fox at 640x480, with the kernels as they are and with the library
   exp put back (two runtimes in one process, alternating, CPU time).

    python bench/exp_neg_probe.py [--data ../shared/data] [--rounds 9]
"""
from __future__ import annotations

import argparse
import re
import time
import warnings
from pathlib import Path

import numpy as np
import pyopencl as cl
import pyopencl.array as cla

warnings.simplefilter("ignore")


def exp_neg_source(rounding: str) -> str:
    """common.h's DEFINE_EXP_NEG with ``rounding`` "magic" (as it is) or "rint"."""
    from qr_cl.runtime import kernel_source
    header = kernel_source("select.cl")
    define = re.search(r"#define DEFINE_EXP_NEG\(.*?\n    }\n", header, re.S).group(0)
    if rounding == "rint":
        define = re.sub(r"const F n = .*?;", "const F n = rint(y * 1.44269504088896341f);", define)
    return define + "DEFINE_EXP_NEG(exp_neg, float, convert_int, as_float)\n" \
                    "DEFINE_EXP_NEG(exp_neg16, float16, convert_int16, as_float16)\n"


KERNELS = """
__kernel void vec(__global const float *x, __global float *y) { int i = get_global_id(0); vstore16(exp_neg16(vload16(i, x)), i, y); }
__kernel void sca(__global const float *x, __global float *y) { int i = get_global_id(0); y[i] = exp_neg(x[i]); }
__kernel void lib_vec(__global const float *x, __global float *y) { int i = get_global_id(0); vstore16(exp(-vload16(i, x)), i, y); }
__kernel void lib_sca(__global const float *x, __global float *y) { int i = get_global_id(0); y[i] = exp(-x[i]); }
__kernel void many(__global const float *x, __global float *y) { int i = get_global_id(0); float16 v = vload16(i, x), s = 0;
    for (int j = 0; j < 256; j++) s += exp_neg16(v + (float)j * 1e-3f); vstore16(s, i, y); }
__kernel void lib_many(__global const float *x, __global float *y) { int i = get_global_id(0); float16 v = vload16(i, x), s = 0;
    for (int j = 0; j < 256; j++) s += exp(-(v + (float)j * 1e-3f)); vstore16(s, i, y); }
"""


def cpu_ms(queue, kernel, x, y, rounds: int) -> float:
    times = []
    for _ in range(rounds):
        start = time.process_time()
        kernel(queue, (x.size // 16,), None, x.data, y.data)
        queue.finish()
        times.append(time.process_time() - start)
    return min(times) * 1e3


def probe_functions(rounds: int) -> None:
    from qr_cl.runtime import runtime
    rt = runtime()
    q = rt.queue
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 30, 1 << 20).astype(np.float32)
    dx, dy = cla.to_device(q, x), cla.empty(q, x.size, np.float32)
    ref = np.exp(-x.astype(np.float64))
    print(f"device: {rt.device.name.strip()} ({rt.device.platform.name.strip()})")
    for rounding in ("magic", "rint"):
        prg = cl.Program(rt.context, exp_neg_source(rounding) + KERNELS).build()
        out = {}
        for name in ("vec", "sca", "lib_vec", "lib_sca"):
            getattr(prg, name)(q, (x.size // 16 if "vec" in name else x.size,), None, dx.data, dy.data)
            out[name] = dy.get()
        ulp = float((np.abs(out["vec"] - ref) / np.spacing(ref.astype(np.float32))).max())
        print(f"exp_neg ({rounding}): vector == scalar: {np.array_equal(out['vec'], out['sca'])}, max {ulp:.2f} ulp; "
              f"library exp vector != scalar in {int((out['lib_vec'] != out['lib_sca']).sum())} of {x.size}; "
              f"256 M exps: exp_neg {cpu_ms(q, prg.many, dx, dy, rounds):.0f} ms, "
              f"library {cpu_ms(q, prg.lib_many, dx, dy, rounds):.0f} ms (CPU)")


def probe_walks(data: Path | None, rounds: int) -> None:
    import qr_cl
    from qr_cl.app.scenes.procedural import dense_room
    from qr_cl.render import rasterize_plan
    from qr_cl.runtime import Runtime, context, padded_rows, runtime, to_device
    from qr_cl.stages import render_fused, select
    scenes = {"dense-room-300k": dense_room()}
    if data is not None and (data / "wakufactory-fox" / "fox.ply").is_file():
        fox = qr_cl.load_ply(data / "wakufactory-fox" / "fox.ply")
        scenes["fox"] = (fox, qr_cl.orbit_cameras(fox.means, 8, 640, 480)[1])
    as_is = context.kernel_source

    def library_exp(name: str) -> str:
        return as_is(name).replace("exp_neg_lanes(sig)", "exp(-(sig))").replace("exp_neg(sig)", "exp(-(sig))")
    builds = {"exp_neg": (runtime(), as_is)}
    builds["library exp"] = (Runtime(builds["exp_neg"][0].device), library_exp)
    plans = {}
    for label, (rt, source) in builds.items():
        context.kernel_source = source
        for name, (g, cam) in scenes.items():
            plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, 640, 480, rt=rt)
            rows = to_device(rt, padded_rows(np.random.default_rng(0).random((plan.n_gaussians, 3), np.float32), 4))
            plans[label, name] = plan, rows
            select(plan, "quantile", 40), select(plan, "volume"), render_fused(plan, rows, 3)   # builds
            rt.queue.finish()
    context.kernel_source = as_is
    calls = {"Q-Render K=40 selection": lambda p, r: select(p, "quantile", 40),
             "V-Render selection": lambda p, r: select(p, "volume"),
             "fused V-Render, 3 channels": lambda p, r: render_fused(p, r, 3)}
    best = {}
    for _ in range(rounds):
        for label in builds:
            for name in scenes:
                plan, rows = plans[label, name]
                for what, call in calls.items():
                    start = time.process_time()
                    call(plan, rows)
                    plan.runtime.queue.finish()
                    key = (name, what, label)
                    best[key] = min(best.get(key, np.inf), time.process_time() - start)
    print("\n| scene | walk | exp_neg ms | library exp ms | ratio |\n| --- | --- | ---: | ---: | ---: |")
    for name in scenes:
        for what in calls:
            a, b = best[name, what, "exp_neg"], best[name, what, "library exp"]
            print(f"| {name} | {what} | {a * 1e3:.1f} | {b * 1e3:.1f} | {a / b:.2f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, help="folder with wakufactory-fox/fox.ply")
    parser.add_argument("--rounds", type=int, default=9)
    args = parser.parse_args()
    probe_functions(args.rounds)
    probe_walks(args.data, args.rounds)


if __name__ == "__main__":
    main()
