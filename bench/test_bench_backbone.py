"""pytest-benchmark of the backbone: MinkUNet14 forward+backward, one convolution vs spconv, peak memory.

Full sizes (20k and 100k occupied voxels of a synthetic room):

    pytest bench/test_bench_backbone.py --benchmark-only

Without ``--benchmark-only`` (or with ``BACKBONE_BENCH_SMOKE=1``) the same tests run once on tiny
voxel sets as a smoke test (a few seconds). ``BACKBONE_BENCH_FULL=1`` forces full sizes.
The spconv rows are skipped when spconv is not installed; its CPU build is a peer reference only
(``spconv_max_abs_diff`` in extra_info records how far its output is from ours: spconv 2.3.8's CPU
build gave wrong rows with more than one OpenMP thread here, and matched dense conv3d with one).
"""

from __future__ import annotations

import os

import pytest
import torch

from backbone_sweep import (UNET_IN_CHANNELS, ours_conv_step, peak_memory, room_voxels, spconv_available,
                            spconv_conv_step, unet_step)
from qr_cl.backbone import KernelMapCache, SparseUNet, minkunet14

FULL_SIZES = {"20k": 20_000, "100k": 100_000}
SMOKE_SIZES = {"20k": 1_000, "100k": 2_000}
CONV_CHANNELS = [(32, 32), (128, 96)]


@pytest.fixture(scope="module")
def full(request) -> bool:
    if os.environ.get("BACKBONE_BENCH_SMOKE") == "1":
        return False
    return os.environ.get("BACKBONE_BENCH_FULL") == "1" or bool(request.config.getoption("benchmark_only", False))


@pytest.fixture(scope="module")
def voxel_sets(full) -> dict[str, torch.Tensor]:
    sizes = FULL_SIZES if full else SMOKE_SIZES
    return {label: room_voxels(n) for label, n in sizes.items()}


def _pedantic(benchmark, fn, full: bool) -> None:
    benchmark.pedantic(fn, rounds=3 if full else 1, iterations=1, warmup_rounds=1 if full else 0)


@pytest.mark.parametrize("maps", ["built", "cached"])
@pytest.mark.parametrize("size", list(FULL_SIZES))
def test_unet_forward_backward(benchmark, voxel_sets, full, size, maps):
    """MinkUNet14 (7 input channels) forward + backward; kernel maps built in the step or cached."""
    torch.manual_seed(0)
    coords = voxel_sets[size]
    unet = SparseUNet(minkunet14(UNET_IN_CHANNELS))
    benchmark.group = f"unet {size}"
    benchmark.extra_info.update(voxels=coords.shape[0], maps=maps, threads=torch.get_num_threads())
    step = unet_step(coords, unet, KernelMapCache() if maps == "cached" else None)
    _pedantic(benchmark, step, full)
    assert all(p.grad is not None for p in unet.parameters())


@pytest.mark.parametrize("channels", CONV_CHANNELS, ids=lambda c: f"{c[0]}to{c[1]}")
@pytest.mark.parametrize("size", list(FULL_SIZES))
@pytest.mark.parametrize("impl", ["ours", "spconv"])
def test_submanifold_conv_forward_backward(benchmark, voxel_sets, full, impl, size, channels):
    """One 3^3 submanifold conv forward + backward, kernel map built in the step (as spconv does)."""
    coords = voxel_sets[size]
    benchmark.group = f"subm conv {size} {channels[0]}->{channels[1]}"
    benchmark.extra_info.update(voxels=coords.shape[0], threads=torch.get_num_threads())
    if impl == "ours":
        step = ours_conv_step(coords, *channels)
    else:
        if not spconv_available():
            pytest.skip("spconv is not installed")
        step, diff = spconv_conv_step(coords, *channels)
        benchmark.extra_info["spconv_max_abs_diff"] = diff
    _pedantic(benchmark, step, full)


def test_unet_peak_memory_100k(benchmark, voxel_sets, full):
    """Peak RSS of one MinkUNet14 forward+backward on the '100k' voxel set, in a fresh process."""
    coords = voxel_sets["100k"]
    result = benchmark.pedantic(peak_memory, args=(coords,), rounds=1, iterations=1)
    benchmark.extra_info.update(result)
    print(f"\npeak memory: {result}")
    assert result["voxels"] == coords.shape[0] and result["peak_rss_mib"] > result["rss_before_mib"] > 0
