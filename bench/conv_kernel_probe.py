"""Would one OpenCL kernel per sparse convolution beat the torch convolution GS-Net trains with?

A probe for the question left by ``bench/training_threads.py`` (a step keeps about 1.4 of 2 cores
busy): its answer decides whether the UNet's layers are worth moving into OpenCL kernels that
PoCL spreads over the cores. The kernel is the simplest output-stationary form: one work-item an
output row, its ``C_out`` sums in registers, a loop over the row's neighbours (a dense
``[n_out, K]`` neighbour table, -1 where a pair is missing) and their ``C_in`` inputs. It is
timed against :func:`qr_cl.backbone.conv.sparse_conv` on two convolution threads (what training
uses), forward only, on the submanifold maps of a demo room's finest level with GS-Net's
channel counts there, alternating the two, and its output is checked against the torch one::

    python bench/conv_kernel_probe.py ~/.cache/qr-cl/scenes/splat-room-0-* --out REPORT.md

The kernel lives here, not in ``kernels/``: it is a measurement, not part of the renderer.
"""
from __future__ import annotations

import statistics
import tempfile
from pathlib import Path

import numpy as np
import pyopencl as cl
import torch

from benchutil import print_table, room_parser, timing
from qr_cl.app.process import cap_kernel_threads, torch_threads
from qr_cl.app.training.config import TrainConfig
from qr_cl.app.training.trainer import Trainer
from qr_cl.backbone import KernelMap, SparseTensor, conv
from qr_cl.runtime import runtime

SOURCE = r"""
// out[r, :] = sum over offsets k with a neighbour j = nbr[r, k] >= 0 of in[j, :] @ w[k]
// (w: [K, CIN, COUT]); one work-item an output row, its COUT sums in registers.
__kernel void conv_rows(__global const float* restrict in, __global const int* restrict nbr,
                        __global const float* restrict w, __global float* restrict out)
{
    const int r = get_global_id(0);
    float acc[COUT];
    for (int co = 0; co < COUT; ++co) acc[co] = 0.0f;
    for (int k = 0; k < KV; ++k) {
        const int j = nbr[r * KV + k];
        if (j < 0) continue;
        __global const float* x = in + (size_t)j * CIN;
        __global const float* wk = w + (size_t)k * CIN * COUT;
        for (int ci = 0; ci < CIN; ++ci) {
            const float xv = x[ci];
            for (int co = 0; co < COUT; ++co) acc[co] += xv * wk[ci * COUT + co];
        }
    }
    for (int co = 0; co < COUT; ++co) out[(size_t)r * COUT + co] = acc[co];
}
"""

#: (kernel size, C_in, C_out) of the finest level's convolutions in GS-Net's "small" UNet: the
#: stem, the last decoder's first block (after the skip concatenation) and its second.
CASES = ((5, 7, 16), (3, 64, 48), (3, 48, 48))


def neighbour_table(kmap: KernelMap) -> np.ndarray:
    """``[n_out, K]`` int32: the input row of output row r through offset k, -1 where none."""
    table = np.full((kmap.n_out, kmap.volume), -1, np.int32)
    for k in range(kmap.volume):
        if k == kmap.identity:
            table[:, k] = np.arange(kmap.n_out)
        else:
            table[kmap.out_idx[k].numpy(), k] = kmap.in_idx[k].numpy()
    return table


def main() -> None:
    parser = room_parser(__doc__)
    parser.add_argument("--rounds", type=int, default=15, help="timed calls of each (default 15)")
    args = parser.parse_args()
    cap_kernel_threads()
    rt = runtime()
    flags = cl.mem_flags
    lines = [f"`python bench/conv_kernel_probe.py {Path(args.room).name} --rounds {args.rounds}` "
             f"({rt.device.name.strip()}, {rt.device.max_compute_units} compute units): forward of one convolution, "
             "median ms; GFLOP/s counts the map's pairs x C_in x C_out x 2", "",
             "| kernel, C_in -> C_out | rows | pairs | torch, 2 threads | one OpenCL kernel | kernel / torch | max rel. difference |",
             "| --- | ---: | ---: | ---: | ---: | ---: | ---: |"]
    with tempfile.TemporaryDirectory() as out, torch_threads(1), conv.conv_threads(2), torch.no_grad():
        trainer = Trainer(TrainConfig(scenes=[args.room], out=out, steps=1))
        try:
            batch = trainer.batch(0)
            SparseTensor(batch.coords, batch.feats, 1, batch.cache)       # registers the finest level's coordinates
            for size, c_in, c_out in CASES:
                kmap = batch.cache.submanifold(1, size)
                gen = torch.Generator().manual_seed(size * 1000 + c_in)
                feats = torch.randn(kmap.n_in, c_in, generator=gen)
                weight = torch.randn(kmap.volume, c_in, c_out, generator=gen) / (kmap.volume * c_in) ** 0.5
                buffers = [cl.Buffer(rt.context, flags.READ_ONLY | flags.COPY_HOST_PTR, hostbuf=a)
                           for a in (feats.numpy(), neighbour_table(kmap), weight.numpy())]
                result = cl.Buffer(rt.context, flags.WRITE_ONLY, kmap.n_out * c_out * 4)
                kernel = cl.Program(rt.context, SOURCE).build(options=f"-DCIN={c_in} -DCOUT={c_out} -DKV={kmap.volume}").conv_rows

                def run_kernel() -> None:
                    kernel(rt.queue, (kmap.n_out,), None, *buffers, result)
                    rt.queue.finish()

                def run_torch() -> torch.Tensor:
                    return conv.sparse_conv(feats, weight, kmap)

                expected = run_torch().numpy()
                run_kernel()
                got = np.empty_like(expected)
                cl.enqueue_copy(rt.queue, got, result)
                diff = float(np.abs(got - expected).max() / np.abs(expected).max())
                torch_ms, kernel_ms = [], []
                for _ in range(3):
                    torch_ms.append(statistics.median(timing.timed_calls(run_torch, args.rounds)[0]) * 1e3)
                    kernel_ms.append(statistics.median(timing.timed_calls(run_kernel, args.rounds)[0]) * 1e3)
                t, k = statistics.median(torch_ms), statistics.median(kernel_ms)
                gflop = kmap.pairs * c_in * c_out * 2 / 1e9
                lines.append(f"| {size}^3, {c_in} -> {c_out} | {kmap.n_out:,} | {kmap.pairs:,} | {t:.2f} ({gflop / t * 1e3:.0f} GFLOP/s) "
                             f"| {k:.2f} ({gflop / k * 1e3:.0f} GFLOP/s) | {k / t:.2f} | {diff:.1e} |")
        finally:
            trainer.close()
    print_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
