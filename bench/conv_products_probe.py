"""Would one call for all of a convolution's per-offset products beat a product per offset?

A probe for the cost of the many small matrix products in GS-Net's sparse convolutions
(:mod:`qr_cl.backbone.conv`): a submanifold 3x3x3 convolution makes one ``[P_k, C_in] @ [C_in,
C_out]`` product per kernel offset k, each tens of microseconds, so per-call costs might matter.
For every 3x3x3 convolution of one forward of GS-Net on a demo room (its real maps and channel
counts, level by level), the products of the whole map are timed three ways on one torch thread,
on the same gathered input rows, alternating:

* ``per offset``: ``torch.mm`` per offset into slices of one output array (what the network runs);
* ``grouped``: one ``torch._grouped_mm`` over all offsets (one call, groups given by offsets);
* ``oneDNN``: ``torch.ops.mkldnn._linear_pointwise`` per offset (oneDNN's fp32 matmul, with the
  AVX-512 kernels it generates where the CPU has them; ``ONEDNN_VERBOSE=1`` names the one used).

Each alternative's products are checked bitwise against the per-offset ones::

    python bench/conv_products_probe.py ~/.cache/qr-cl/scenes/splat-room-0-* --out REPORT.md
"""
from __future__ import annotations

import statistics
import tempfile
from pathlib import Path

import torch

from benchutil import print_table, room_parser, timing
from qr_cl.app.process import torch_threads
from qr_cl.app.training.config import TrainConfig
from qr_cl.app.training.trainer import Trainer
from qr_cl.backbone import KernelMap, conv


def network_convolutions(trainer: Trainer) -> list[tuple[KernelMap, int, int]]:
    """(map, C_in, C_out) of each 3x3x3 convolution of one forward of the trainer's GS-Net on its
    first scene, in the order the network runs them."""
    seen = []
    inner = conv.sparse_conv

    def recording(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap) -> torch.Tensor:
        if kmap.volume == 27:
            seen.append((kmap, weight.shape[1], weight.shape[2]))
        return inner(feats, weight, kmap)

    conv.sparse_conv = recording
    try:
        with torch.no_grad():
            batch = trainer.batch(0)
            trainer.net.head_inputs(batch, torch.arange(len(batch.feats)))
    finally:
        conv.sparse_conv = inner
    return seen


def product_variants(kmap: KernelMap, c_in: int, c_out: int) -> tuple[dict, int]:
    """{name: call} computing the map's per-offset products ``[P, C_out]`` three ways from random
    gathered rows ``[P, C_in]`` (P: the map's pairs without the identity's), and P."""
    block = kmap.row_blocks(1)[0]
    sizes = [block.bounds[k + 1] - block.bounds[k] for k in range(kmap.volume)]
    gen = torch.Generator().manual_seed(c_in * 1000 + c_out)
    gathered = torch.randn(sum(sizes), c_in, generator=gen)
    weight = torch.randn(kmap.volume, c_in, c_out, generator=gen)
    weight_t = weight.transpose(1, 2).contiguous()
    offsets = torch.tensor(sizes).cumsum(0).to(torch.int32)
    products = torch.empty(sum(sizes), c_out)

    def per_offset() -> torch.Tensor:
        for g, w, p in zip(gathered.split(sizes), weight.unbind(0), products.split(sizes)):
            if g.shape[0]:
                torch.mm(g, w, out=p)
        return products

    def grouped() -> torch.Tensor:
        return torch._grouped_mm(gathered, weight, offs=offsets)

    def onednn() -> torch.Tensor:
        return torch.cat([torch.ops.mkldnn._linear_pointwise(g, w, None, "none", [], "")
                          for g, w in zip(gathered.split(sizes), weight_t.unbind(0)) if g.shape[0]])

    return {"per offset": per_offset, "grouped": grouped, "oneDNN": onednn}, sum(sizes)


def main() -> None:
    parser = room_parser(__doc__)
    parser.add_argument("--calls", type=int, default=30, help="timed calls of each, per round (default 30)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds, alternating the three (default 3)")
    args = parser.parse_args()
    names = ("per offset", "grouped", "oneDNN")
    lines = [f"`python bench/conv_products_probe.py {Path(args.room).name} --calls {args.calls} --rounds {args.rounds}` "
             "(one torch thread): the per-offset products of each 3x3x3 convolution of one GS-Net forward, "
             "median microseconds; in brackets the time over the per-offset time, and whether the products "
             "are bitwise the per-offset ones", "",
             "| rows | pairs | C_in -> C_out | per offset | grouped | oneDNN |", "| ---: | ---: | --- | ---: | ---: | ---: |"]
    totals = dict.fromkeys(names, 0.0)
    with tempfile.TemporaryDirectory() as out, torch_threads(1):
        trainer = Trainer(TrainConfig(scenes=[args.room], out=out, steps=1))
        try:
            convolutions = network_convolutions(trainer)
        finally:
            trainer.close()
        for kmap, c_in, c_out in convolutions:
            calls, pairs = product_variants(kmap, c_in, c_out)
            expected = calls["per offset"]().clone()
            same = {name: torch.equal(call(), expected) for name, call in calls.items()}
            times = {name: [] for name in names}
            for _ in range(args.rounds):
                for name in names:
                    calls[name]()
                    times[name].extend(timing.timed_calls(calls[name], args.calls)[0])
            us = {name: statistics.median(t) * 1e6 for name, t in times.items()}
            for name in names:
                totals[name] += us[name]
            cells = [f"{us[n]:.0f}" if n == "per offset" else
                     f"{us[n]:.0f} ({us[n] / us['per offset']:.2f}, {'same' if same[n] else 'differs'})" for n in names]
            lines.append(f"| {kmap.n_out:,} | {pairs:,} | {c_in} -> {c_out} | " + " | ".join(cells) + " |")
    lines.append(f"| all {len(convolutions)} | | | {totals['per offset']:.0f} | "
                 + " | ".join(f"{totals[n]:.0f} ({totals[n] / totals['per offset']:.2f})" for n in names[1:]) + " |")
    print_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
