"""Sparse convolutions of backbone.conv against torch.nn.functional.conv3d on dense grids, and split
over threads: bitwise the same on 1 or 2 threads and run to run."""

import os
import subprocess
import sys
import threading

import pytest
import torch
import torch.nn.functional as F

from qr_cl.backbone import SparseUNet, conv, minkunet14
from qr_cl.backbone.conv import (DownsampleConv3d, SparseBatchNorm, SubmanifoldConv3d, UpsampleConv3d, conv_threads,
                                 get_conv_threads, set_conv_threads, sparse_conv)
from qr_cl.backbone.sparse import KernelMap, SparseTensor

GRID = 8
BATCH = 2


def random_sparse(channels: int, occupancy: float, seed: int) -> SparseTensor:
    """Random occupancy of a [BATCH, GRID^3] grid, rows shuffled, float64 features needing grad."""
    g = torch.Generator().manual_seed(seed)
    coords = torch.nonzero(torch.rand(BATCH, GRID, GRID, GRID, generator=g) < occupancy)
    coords = coords[torch.randperm(coords.shape[0], generator=g)]
    feats = torch.randn(coords.shape[0], channels, generator=g, dtype=torch.float64)
    return SparseTensor(coords, feats.requires_grad_())


def to_dense(coords: torch.Tensor, feats: torch.Tensor, size: int, step: int = 1) -> torch.Tensor:
    dense = feats.new_zeros(BATCH, size, size, size, feats.shape[1])
    c = coords[:, 1:] // step
    return dense.index_put((coords[:, 0], c[:, 0], c[:, 1], c[:, 2]), feats).permute(0, 4, 1, 2, 3)


def at_sites(dense: torch.Tensor, coords: torch.Tensor, step: int = 1) -> torch.Tensor:
    c = coords[:, 1:] // step
    return dense[coords[:, 0], :, c[:, 0], c[:, 1], c[:, 2]]


def compare(sparse_out, dense_out, inputs, seed):
    """Forward values and the gradients of a random linear loss of both outputs w.r.t. inputs."""
    g = torch.Generator().manual_seed(seed)
    probe = torch.randn(sparse_out.shape, generator=g, dtype=sparse_out.dtype)
    torch.testing.assert_close(sparse_out, dense_out, rtol=1e-10, atol=1e-10)
    grads_sparse = torch.autograd.grad((sparse_out * probe).sum(), inputs)
    grads_dense = torch.autograd.grad((dense_out * probe).sum(), inputs)
    assert all(gs.abs().sum() > 0 for gs in grads_sparse)
    for gs, gd in zip(grads_sparse, grads_dense):
        torch.testing.assert_close(gs, gd, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("kernel_size", [3, 5])
def test_submanifold_equals_dense_conv3d(kernel_size):
    torch.manual_seed(0)
    x = random_sparse(3, 0.3, seed=kernel_size)
    conv = SubmanifoldConv3d(3, 4, kernel_size, bias=True).double()
    y = conv(x)
    k = kernel_size
    dense_w = conv.weight.reshape(k, k, k, 3, 4).permute(4, 3, 0, 1, 2)
    ref = F.conv3d(to_dense(x.coords, x.feats, GRID), dense_w, conv.bias, padding=k // 2)
    assert torch.equal(y.coords, x.coords)
    compare(y.feats, at_sites(ref, x.coords), (x.feats, conv.weight, conv.bias), seed=1)


def test_downsample_equals_dense_strided_conv3d():
    torch.manual_seed(0)
    x = random_sparse(3, 0.2, seed=7)
    conv = DownsampleConv3d(3, 5).double()
    y = conv(x)
    dense_w = conv.weight.reshape(2, 2, 2, 3, 5).permute(4, 3, 0, 1, 2)
    ref = F.conv3d(to_dense(x.coords, x.feats, GRID), dense_w, stride=2)
    occupied = to_dense(x.coords, torch.ones(len(x), 1, dtype=torch.float64), GRID)
    parents = F.max_pool3d(occupied, 2).sum()
    assert y.stride == 2 and len(y) == int(parents)
    assert bool((y.coords[:, 1:] % 2 == 0).all())
    compare(y.feats, at_sites(ref, y.coords, 2), (x.feats, conv.weight), seed=2)


def test_upsample_equals_dense_conv_transpose3d_on_finer_sites():
    torch.manual_seed(0)
    x = random_sparse(3, 0.25, seed=11)
    coarse = DownsampleConv3d(3, 4).double()(x)
    z = coarse.with_feats(coarse.feats.detach().requires_grad_())
    up = UpsampleConv3d(4, 2).double()
    y = up(z)
    assert y.stride == 1 and torch.equal(y.coords, x.coords)
    dense_w = up.weight.reshape(2, 2, 2, 4, 2).permute(3, 4, 0, 1, 2)
    ref = F.conv_transpose3d(to_dense(z.coords, z.feats, GRID // 2, step=2), dense_w, stride=2)
    compare(y.feats, at_sites(ref, x.coords), (z.feats, up.weight), seed=3)


def test_gradcheck_of_sparse_conv():
    x = random_sparse(2, 0.15, seed=5)
    w = torch.randn(27, 2, 3, dtype=torch.float64, requires_grad=True)
    kmap = x.cache.submanifold(1, 3)
    assert torch.autograd.gradcheck(lambda f, w: sparse_conv(f, w, kmap), (x.feats, w))
    down = x.cache.downsample(1)
    w8 = torch.randn(8, 2, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda f, w: sparse_conv(f, w, down), (x.feats, w8))


@pytest.mark.parametrize("shift", [(0, 0, 0), (5, -3, 1), (-1000, 24, 7)])
def test_translation_equivariance(shift):
    torch.manual_seed(0)
    x = random_sparse(3, 0.3, seed=13)
    conv = SubmanifoldConv3d(3, 4).double()
    moved = x.coords.clone()
    moved[:, 1:] += torch.tensor(shift)
    y0 = conv(x).feats
    y1 = conv(SparseTensor(moved, x.feats)).feats
    torch.testing.assert_close(y0, y1, rtol=1e-12, atol=1e-12)
    if all(s % 2 == 0 for s in shift):
        down = DownsampleConv3d(3, 4).double()
        torch.testing.assert_close(down(x).feats, down(SparseTensor(moved, x.feats)).feats, rtol=1e-12, atol=1e-12)


def test_scenes_in_a_batch_do_not_mix():
    torch.manual_seed(0)
    x = random_sparse(3, 0.3, seed=17)
    conv = SubmanifoldConv3d(3, 4).double()
    y = conv(x).feats
    for b in range(BATCH):
        rows = torch.nonzero(x.coords[:, 0] == b).squeeze(1)
        alone = x.coords[rows].clone()
        alone[:, 0] = 0
        torch.testing.assert_close(conv(SparseTensor(alone, x.feats[rows])).feats, y[rows], rtol=1e-12, atol=1e-12)


def test_empty_input():
    x = SparseTensor(torch.zeros(0, 4, dtype=torch.int64), torch.zeros(0, 3, requires_grad=True))
    sub, down, up = SubmanifoldConv3d(3, 4), DownsampleConv3d(4, 6), UpsampleConv3d(6, 2)
    y = up(down(sub(x)))
    assert y.feats.shape == (0, 2) and y.stride == 1
    y.feats.sum().backward()
    assert x.feats.grad.shape == (0, 3)
    assert torch.equal(sub.weight.grad, torch.zeros_like(sub.weight))


def test_single_voxel():
    torch.manual_seed(0)
    x = SparseTensor(torch.tensor([[0, -3, 4, 5]]), torch.randn(1, 3, dtype=torch.float64))
    sub = SubmanifoldConv3d(3, 4).double()
    torch.testing.assert_close(sub(x).feats, x.feats @ sub.weight[13])
    down = DownsampleConv3d(3, 2).double()
    y = down(x)
    assert y.coords.tolist() == [[0, -4, 4, 4]]
    torch.testing.assert_close(y.feats, x.feats @ down.weight[4 * 1 + 2 * 0 + 1])
    up = UpsampleConv3d(2, 3).double()
    assert torch.equal(up(y).coords, x.coords)
    bn = SparseBatchNorm(3).double().train()
    out = bn(x).feats
    torch.testing.assert_close(out, x.feats / (1 + bn.eps) ** 0.5)
    assert bn.num_batches_tracked.item() == 0


def test_bad_weight_shape_is_named():
    x = random_sparse(3, 0.2, seed=1)
    with pytest.raises(ValueError, match="weight"):
        sparse_conv(x.feats, torch.zeros(27, 2, 4, dtype=torch.float64), x.cache.submanifold(1, 3))
    with pytest.raises(ValueError, match="odd"):
        SubmanifoldConv3d(3, 4, kernel_size=4)


def conv_and_grads(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap, seed: int) -> list[torch.Tensor]:
    """Output, d feats and d weight of a random linear loss of ``sparse_conv``."""
    f = feats.detach().requires_grad_()
    w = weight.detach().requires_grad_()
    y = sparse_conv(f, w, kmap)
    probe = torch.randn(y.shape, generator=torch.Generator().manual_seed(seed))
    (y * probe).sum().backward()
    return [y.detach(), f.grad, w.grad]


def reference_conv(feats: torch.Tensor, weight: torch.Tensor, kmap: KernelMap) -> torch.Tensor:
    """The convolution as one gather, product and scatter per offset over all pairs (no blocks)."""
    out = feats @ weight[kmap.identity] if kmap.identity is not None else feats.new_zeros(kmap.n_out, weight.shape[2])
    for k, (src, dst) in enumerate(zip(kmap.in_idx, kmap.out_idx)):
        if k != kmap.identity:
            out = out.index_add(0, dst, feats[src] @ weight[k])
    return out


def float_maps() -> list[tuple[KernelMap, int, int]]:
    """(map, C_in, C_out) of a submanifold, a down- and an up-sampling convolution on float32 voxels."""
    x = random_sparse(3, 0.5, seed=23)
    return [(x.cache.submanifold(1, 3), 5, 7), (x.cache.downsample(1), 6, 4), (x.cache.upsample(2), 4, 6)]


@pytest.fixture
def split_small_maps(monkeypatch):
    """Split every map with 64 or more pairs (the default threshold keeps test-sized maps whole)."""
    monkeypatch.setattr(conv, "MIN_SPLIT_PAIRS", 64)


def test_split_convolution_is_bitwise_the_same_on_one_or_two_threads_and_run_to_run(split_small_maps):
    g = torch.Generator().manual_seed(0)
    for kmap, c_in, c_out in float_maps():
        assert len(conv._blocks(kmap)) == conv.SPLIT
        feats, weight = torch.randn(kmap.n_in, c_in, generator=g), torch.randn(kmap.volume, c_in, c_out, generator=g)
        with conv_threads(1):
            one = conv_and_grads(feats, weight, kmap, seed=1)
        with conv_threads(2):
            runs = [conv_and_grads(feats, weight, kmap, seed=1) for _ in range(3)]
        for two in runs:
            assert all(torch.equal(a, b) for a, b in zip(one, two))


def test_split_forward_is_bitwise_the_whole_map_and_backward_within_rounding(split_small_maps):
    """A row of a product does not depend on the other rows, so the forward of the blocks is that
    of all pairs at once; the backward sums the weight gradient over the blocks and adds the
    identity's rows first: float rounding only."""
    g = torch.Generator().manual_seed(1)
    for kmap, c_in, c_out in float_maps():
        feats, weight = torch.randn(kmap.n_in, c_in, generator=g), torch.randn(kmap.volume, c_in, c_out, generator=g)
        with conv_threads(2):
            split = conv_and_grads(feats, weight, kmap, seed=2)
        f, w = feats.clone().requires_grad_(), weight.clone().requires_grad_()
        ref = reference_conv(f, w, kmap)
        probe = torch.randn(ref.shape, generator=torch.Generator().manual_seed(2))
        (ref * probe).sum().backward()
        assert torch.equal(split[0], ref)
        torch.testing.assert_close(split[1], f.grad, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(split[2], w.grad, rtol=1e-5, atol=1e-5)


def test_a_block_no_helper_started_is_run_by_the_caller(split_small_maps):
    kmap, c_in, c_out = float_maps()[0]
    g = torch.Generator().manual_seed(2)
    feats, weight = torch.randn(kmap.n_in, c_in, generator=g), torch.randn(kmap.volume, c_in, c_out, generator=g)
    with conv_threads(1):
        one = conv_and_grads(feats, weight, kmap, seed=3)
    release = threading.Event()
    with conv_threads(2):
        busy = conv._helpers.submit(release.wait)     # the only helper is held up
        try:
            two = conv_and_grads(feats, weight, kmap, seed=3)
        finally:
            release.set()
        busy.result()
    assert all(torch.equal(a, b) for a, b in zip(one, two))


def test_unet_training_step_is_bitwise_the_same_on_one_or_two_threads(split_small_maps):
    coords = random_sparse(1, 0.4, seed=29).coords
    config = minkunet14(4, stem_channels=8, enc_channels=(8, 16), enc_blocks=(1, 1), dec_channels=(16, 8),
                        dec_blocks=(1, 1))
    results = []
    for threads in (1, 2, 2):
        torch.manual_seed(0)
        net = SparseUNet(config).train()
        feats = torch.randn(coords.shape[0], 4)
        with conv_threads(threads):
            out = net(SparseTensor(coords, feats)).feats
            loss = (out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum()
            loss.backward()
        results.append([loss.detach()] + [p.grad for p in net.parameters()])
    for other in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))


def test_conv_threads_are_set_and_restored():
    before = get_conv_threads()
    with conv_threads(2):
        assert get_conv_threads() == 2 and conv._helpers is not None
    assert get_conv_threads() == before
    with pytest.raises(ValueError, match="threads"):
        set_conv_threads(0)


def test_a_helper_runs_torch_on_the_callers_intra_op_threads():
    """A fresh process with one torch thread: the helper's products start no OpenMP team (a new
    thread's first torch op took OpenMP's default, every core, so two helpers' cores each)."""
    script = """
import os, torch
torch.set_num_threads(1)
from qr_cl.backbone import conv
a, b = torch.randn(2000, 48), torch.randn(48, 48)     # a convolution's product at one offset
with conv.conv_threads(2):
    conv._helpers.submit(int).result()
    before = len(os.listdir("/proc/self/task"))
    conv._helpers.submit(lambda: [torch.mm(a, b) for _ in range(200)]).result()   # no torch call before
    print(len(os.listdir("/proc/self/task")) - before)
"""
    if not os.path.isdir("/proc/self/task"):
        pytest.skip("needs /proc to count threads")
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["0"], f"threads started by the helper's products: {run.stdout}"
