"""Timing and memory of the backbone's sparse UNet and convolution, with spconv as a peer when installed.

Synthetic room-like voxel sets (floor, four walls, a dozen spheres: surfaces, as Gaussians are):

    python bench/backbone_sweep.py unet --voxels 20000 100000   # UNet forward+backward, cold and cached maps
    python bench/backbone_sweep.py conv --voxels 20000 100000   # one conv, ours vs spconv, interleaved
    python bench/backbone_sweep.py memory --voxels 100000       # peak RSS of one UNet forward+backward

``bench/test_bench_backbone.py`` runs the same workloads under pytest-benchmark.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

import torch

from qr_cl.app.timing import measure
from qr_cl.backbone import KernelMapCache, SparseTensor, SparseUNet, SubmanifoldConv3d, minkunet14

UNET_IN_CHANNELS = 7


def room_voxels(count: int, seed: int = 0) -> torch.Tensor:
    """Exactly ``count`` occupied voxels ``[count, 4]`` int64 (batch 0, x, y, z >= 0) of a room's surfaces."""
    g = torch.Generator().manual_seed(seed)
    side = math.sqrt(1.15 * count / 3.2)
    height = 0.3 * side
    planes = [
        ((0, 0, 0), (side, 0, 0), (0, side, 0)),
        ((0, 0, 0), (side, 0, 0), (0, 0, height)),
        ((0, side, 0), (side, 0, 0), (0, 0, height)),
        ((0, 0, 0), (0, side, 0), (0, 0, height)),
        ((side, 0, 0), (0, side, 0), (0, 0, height)),
    ]
    points = 12 * count
    parts = []
    for origin, u, v in planes:
        n = int(0.7 * points * (math.dist(u, (0, 0, 0)) * math.dist(v, (0, 0, 0))) / (side * side + 4 * side * height))
        a, b = torch.rand(n, 1, generator=g), torch.rand(n, 1, generator=g)
        parts.append(torch.tensor(origin) + a * torch.tensor(u) + b * torch.tensor(v))
    centres = torch.rand(12, 3, generator=g) * torch.tensor([side, side, 0.5 * height])
    radii = (torch.rand(12, 1, generator=g) * 0.08 + 0.04) * side
    dirs = torch.nn.functional.normalize(torch.randn(int(0.3 * points), 3, generator=g), dim=1)
    which = torch.randint(0, 12, (dirs.shape[0],), generator=g)
    parts.append(centres[which] + radii[which] * dirs)
    voxels = torch.unique(torch.floor(torch.cat(parts)).long(), dim=0)
    if voxels.shape[0] < count:
        raise RuntimeError(f"the room generator made {voxels.shape[0]} voxels, fewer than {count}")
    voxels = voxels[:count]
    voxels -= voxels.min(0).values
    return torch.cat([torch.zeros(count, 1, dtype=torch.int64), voxels], 1)


def unet_step(coords: torch.Tensor, unet: SparseUNet, cache: KernelMapCache | None) -> Callable[[], None]:
    """One forward+backward of ``unet`` on ``coords`` with random features; a fresh map cache when ``cache`` is None."""
    feats = torch.randn(coords.shape[0], UNET_IN_CHANNELS, generator=torch.Generator().manual_seed(1))

    def run() -> None:
        unet.zero_grad(set_to_none=True)
        out = unet(SparseTensor(coords, feats, 1, cache if cache is not None else KernelMapCache()))
        out.feats.square().mean().backward()

    return run


def ours_conv_step(coords: torch.Tensor, c_in: int, c_out: int) -> Callable[[], None]:
    """Forward+backward of one 3^3 submanifold conv, kernel map built inside (as spconv does)."""
    torch.manual_seed(0)
    conv = SubmanifoldConv3d(c_in, c_out)
    feats = torch.randn(coords.shape[0], c_in, requires_grad=True)

    def run() -> None:
        feats.grad = None
        conv.zero_grad(set_to_none=True)
        conv(SparseTensor(coords, feats)).feats.square().mean().backward()

    return run


def spconv_available() -> bool:
    """True when spconv's PyTorch API imports."""
    try:
        import spconv.pytorch  # noqa: F401
    except ImportError:
        return False
    return True


def spconv_conv_step(coords: torch.Tensor, c_in: int, c_out: int) -> tuple[Callable[[], None], float]:
    """spconv's SubMConv3d doing what :func:`ours_conv_step` does, and the largest output difference.

    spconv's CPU build queries a CUDA stream in its backward; on a CPU-only torch that stream is
    patched to 0 (the CPU kernels ignore it).
    """
    import spconv.pytorch as spconv
    from spconv.pytorch import ops

    if not torch.cuda.is_available():
        ops.get_current_stream = lambda: 0
    torch.manual_seed(0)
    ours = SubmanifoldConv3d(c_in, c_out)
    conv = spconv.SubMConv3d(c_in, c_out, 3, bias=False, algo=spconv.ConvAlgo.Native)
    with torch.no_grad():
        conv.weight.copy_(ours.weight.reshape(3, 3, 3, c_in, c_out).permute(4, 0, 1, 2, 3))
    feats = torch.randn(coords.shape[0], c_in, requires_grad=True)
    indices = coords.to(torch.int32).contiguous()
    shape = (coords[:, 1:].max(0).values + 1).tolist()

    def forward() -> torch.Tensor:
        return conv(spconv.SparseConvTensor(feats, indices, shape, 1)).features

    def run() -> None:
        feats.grad = None
        conv.zero_grad(set_to_none=True)
        forward().square().mean().backward()

    with torch.no_grad():
        diff = float((forward() - ours(SparseTensor(coords, feats)).feats).abs().max())
    return run, diff


def peak_memory(coords: torch.Tensor) -> dict:
    """Peak RSS (MiB) of a fresh process doing one MinkUNet14 forward+backward on ``coords`` ``[M, 4]``.

    The coordinates travel through a temporary file so that generating them does not raise the
    child's high-water mark; ``step_peak_mib`` is the peak minus the RSS after loading them and
    building the model.
    """
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "coords.pt"
        torch.save(coords, path)
        cmd = [sys.executable, str(Path(__file__).resolve()), "memory-child", "--coords", str(path)]
        out = subprocess.run(cmd, check=True, capture_output=True, text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _high_water_mib() -> float:
    """This process's peak RSS in MiB: VmHWM (reset by exec, unlike ru_maxrss, which a child
    inherits from the parent it was forked from), or ru_maxrss where /proc is missing."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _memory_child(path: str) -> None:
    coords = torch.load(path)
    unet = SparseUNet(minkunet14(UNET_IN_CHANNELS))
    step = unet_step(coords, unet, None)
    before = _high_water_mib()
    step()
    peak = _high_water_mib()
    print(json.dumps({"voxels": coords.shape[0], "rss_before_mib": round(before, 1), "peak_rss_mib": round(peak, 1),
                      "step_peak_mib": round(peak - before, 1)}))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["unet", "conv", "memory", "memory-child"])
    parser.add_argument("--voxels", type=int, nargs="+", default=[20000, 100000])
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--channels", type=int, nargs=2, action="append", help="conv C_in C_out (repeatable)")
    parser.add_argument("--coords", help="memory-child: file of coordinates written by peak_memory")
    args = parser.parse_args()
    if args.what == "memory-child":
        _memory_child(args.coords)
        return
    for n in args.voxels:
        if args.what == "memory":
            print(json.dumps(peak_memory(room_voxels(n))))
        elif args.what == "unet":
            coords = room_voxels(n)
            unet = SparseUNet(minkunet14(UNET_IN_CHANNELS))
            cold = measure(unet_step(coords, unet, None), args.rounds)["min_s"]
            cache = KernelMapCache()
            cached = measure(unet_step(coords, unet, cache), args.rounds)["min_s"]
            print(f"MinkUNet14 fwd+bwd, {n} voxels: {cold:.3f} s with map building, {cached:.3f} s with cached maps")
        else:
            coords = room_voxels(n)
            for c_in, c_out in args.channels or [(32, 32), (128, 96)]:
                ours = measure(ours_conv_step(coords, c_in, c_out), args.rounds)["min_s"]
                line = f"subm 3^3 conv {c_in}->{c_out} fwd+bwd, {n} voxels: ours {ours:.4f} s"
                if spconv_available():
                    run, diff = spconv_conv_step(coords, c_in, c_out)
                    peer = measure(run, args.rounds)["min_s"]
                    line += f", spconv {peer:.4f} s, ours/spconv {ours / peer:.2f} (max |diff| {diff:.2e})"
                print(line)


if __name__ == "__main__":
    main()
