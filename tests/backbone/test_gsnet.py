"""SparseUNet and GSNet: shapes, unit outputs, equivariance, batching, caching and a tiny overfit."""

import pytest
import torch
import torch.nn.functional as F

from qr_cl.backbone import GSNet, SparseTensor, SparseUNet, VoxelConfig, devoxelize, minkunet14, minkunet18
from qr_cl.scene import Gaussians

SMALL = dict(stem_channels=8, stem_kernel=3, enc_channels=(8, 16, 16), enc_blocks=(1, 1, 1), dec_channels=(16, 8, 8), dec_blocks=(1, 1, 1))


def random_gaussians(n: int, seed: int) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians.from_rgb(
        torch.rand(n, 3, generator=g) * 0.6, torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) * 0.03 + 1e-3,
        torch.rand(n, generator=g) * 0.9 + 0.05, torch.rand(n, 3, generator=g),
    )


def surface_voxels(seed: int) -> torch.Tensor:
    """A bumpy sheet of voxels in one scene, [M, 4]."""
    g = torch.Generator().manual_seed(seed)
    ij = torch.cartesian_prod(torch.arange(20), torch.arange(20))
    k = (2 * torch.sin(ij[:, 0] / 3.0)).round().long() + torch.randint(0, 2, (ij.shape[0],), generator=g)
    return torch.cat([torch.zeros(ij.shape[0], 1, dtype=torch.int64), ij, k[:, None]], 1)


def test_unet_keeps_voxels_and_gives_configured_width():
    torch.manual_seed(0)
    coords = surface_voxels(0)
    unet = SparseUNet(minkunet14(5, **SMALL))
    out = unet(SparseTensor(coords, torch.randn(coords.shape[0], 5)))
    assert torch.equal(out.coords, coords) and out.stride == 1
    assert out.feats.shape == (coords.shape[0], unet.out_channels) == (coords.shape[0], 8)
    out.feats.square().sum().backward()
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in unet.parameters())


def test_minkunet_plans():
    a, b = minkunet14(7), minkunet18(7)
    assert a.enc_channels == b.enc_channels == (32, 64, 128, 256) and a.dec_channels == (256, 128, 96, 96)
    assert a.enc_blocks == (1, 1, 1, 1) and b.enc_blocks == (2, 2, 2, 2)
    n14 = sum(p.numel() for p in SparseUNet(a).parameters())
    n18 = sum(p.numel() for p in SparseUNet(b).parameters())
    assert n18 > n14
    with pytest.raises(ValueError, match="dec_channels"):
        minkunet14(7, dec_channels=(96,))


def test_unet_is_translation_equivariant_for_shifts_of_its_coarsest_stride():
    torch.manual_seed(0)
    coords = surface_voxels(1)
    feats = torch.randn(coords.shape[0], 5, dtype=torch.float64)
    unet = SparseUNet(minkunet14(5, **SMALL)).double().eval()
    with torch.no_grad():
        for m in unet.modules():
            if isinstance(m, torch.nn.BatchNorm1d):
                m.running_mean.uniform_(-0.1, 0.1)
                m.running_var.uniform_(0.5, 1.5)
        y0 = unet(SparseTensor(coords, feats)).feats
        moved = coords + torch.tensor([0, 8 * 7, -8 * 3, 8 * 1000])
        y1 = unet(SparseTensor(moved, feats)).feats
        odd = unet(SparseTensor(coords + torch.tensor([0, 1, 0, 0]), feats)).feats
    torch.testing.assert_close(y0, y1, rtol=1e-10, atol=1e-10)
    assert not torch.allclose(y0, odd)


def test_batched_scenes_match_separate_runs_in_eval_mode():
    torch.manual_seed(0)
    net = GSNet(16, VoxelConfig(grid_size=0.05), minkunet14(7, **SMALL)).eval()
    a, b = random_gaussians(300, 1), random_gaussians(200, 2)
    with torch.no_grad():
        batch = net.prepare([a, b])
        fa, fb = batch.split(net(batch))
        torch.testing.assert_close(fa, net(net.prepare(a)), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(fb, net(net.prepare([b])), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("shape, reduce", [("center", "max"), ("volume", "max"), ("volume", "mean")])
def test_gsnet_outputs_unit_vectors(shape, reduce):
    torch.manual_seed(0)
    cfg = VoxelConfig(grid_size=0.05, sample_shape=shape, use_scale=True, use_rotation=True)
    net = GSNet(voxel_config=cfg, unet_config=minkunet14(cfg.num_features, **SMALL), reduce=reduce)
    batch = net.prepare([random_gaussians(150, 3), random_gaussians(50, 4)])
    out = net(batch)
    assert out.shape == (200, 512)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(200))
    out[:, 0].sum().backward()
    assert net.head.weight.grad.abs().sum() > 0


def test_head_before_mean_devoxelization_equals_head_after():
    torch.manual_seed(0)
    cfg = VoxelConfig(grid_size=0.05, sample_shape="volume")
    net = GSNet(24, cfg, minkunet14(7, **SMALL), reduce="mean").eval()
    batch = net.prepare(random_gaussians(100, 5))
    assert not batch.one_sample_per_gaussian
    with torch.no_grad():
        voxels = net.unet(SparseTensor(batch.coords, batch.feats, 1, batch.cache)).feats
        expected = F.normalize(net.head(devoxelize(voxels, batch, "mean")), dim=1)
        torch.testing.assert_close(net(batch), expected, rtol=1e-5, atol=1e-6)


def test_kernel_maps_are_built_once_per_batch():
    torch.manual_seed(0)
    net = GSNet(8, VoxelConfig(grid_size=0.05), minkunet14(7, **SMALL)).eval()
    batch = net.prepare(random_gaussians(300, 6))
    with torch.no_grad():
        first = net(batch)
        built = len(batch.cache)
        stem_map, down_map = batch.cache.submanifold(1, 3), batch.cache.downsample(1)
        second = net(batch)
    assert built == 3 + 3 + 1
    assert len(batch.cache) == built
    assert batch.cache.submanifold(1, 3) is stem_map and batch.cache.downsample(1) is down_map
    torch.testing.assert_close(first, second, rtol=0, atol=0)


def test_empty_and_single_gaussian_scenes():
    torch.manual_seed(0)
    net = GSNet(8, VoxelConfig(grid_size=0.05), minkunet14(7, **SMALL))
    empty = Gaussians.from_rgb(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3))
    assert net(net.prepare(empty)).shape == (0, 8)
    one = random_gaussians(1, 7)
    out = net(net.prepare(one))
    assert out.shape == (1, 8)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(1))


def test_mismatched_configs_are_rejected():
    with pytest.raises(ValueError, match="in_channels"):
        GSNet(8, VoxelConfig(use_scale=True), minkunet14(7))
    net = GSNet(8, VoxelConfig(grid_size=0.05), minkunet14(7, **SMALL))
    other = GSNet(8, VoxelConfig(grid_size=0.1), minkunet14(7, **SMALL))
    with pytest.raises(ValueError, match="voxel config"):
        net(other.prepare(random_gaussians(10, 8)))
    with pytest.raises(ValueError, match="reduce"):
        GSNet(8, reduce="sum")
    with pytest.raises(TypeError, match="prepare"):
        net(random_gaussians(10, 9))


def test_unet_rejects_nan_and_wrong_widths():
    unet = SparseUNet(minkunet14(5, **SMALL))
    coords = surface_voxels(2)
    feats = torch.zeros(coords.shape[0], 5)
    feats[3, 1] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        unet(SparseTensor(coords, feats))
    with pytest.raises(ValueError, match="5 input channels"):
        unet(SparseTensor(coords, torch.zeros(coords.shape[0], 4)))


def three_clusters(n: int, seed: int) -> tuple[Gaussians, torch.Tensor]:
    """A sheet, a rod and a ball of Gaussians with the same colour, scale and opacity statistics."""
    g = torch.Generator().manual_seed(seed)
    sheet = torch.cat([torch.rand(n, 2, generator=g) * 0.8, 0.01 * torch.randn(n, 1, generator=g)], 1)
    rod = torch.cat([0.01 * torch.randn(n, 2, generator=g), torch.rand(n, 1, generator=g) * 0.8], 1) + torch.tensor([1.2, 0.0, 0.0])
    ball = torch.randn(n, 3, generator=g) * 0.12 + torch.tensor([0.0, 1.2, 0.0])
    m = 3 * n
    gaussians = Gaussians.from_rgb(
        torch.cat([sheet, rod, ball]), torch.randn(m, 4, generator=g), torch.rand(m, 3, generator=g) * 0.02 + 0.005,
        torch.rand(m, generator=g) * 0.9 + 0.05, torch.rand(m, 3, generator=g),
    )
    return gaussians, torch.arange(3).repeat_interleave(n)


def test_gsnet_overfits_three_labelled_clusters():
    torch.manual_seed(0)
    gaussians, labels = three_clusters(200, seed=0)
    net = GSNet()
    targets = F.normalize(torch.randn(3, net.feature_dim), dim=1)
    batch = net.prepare(gaussians)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    net.train()
    for _ in range(40):
        loss = F.cross_entropy(net(batch) @ targets.T / 0.1, labels)
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    with torch.no_grad():
        accuracy = ((net(batch) @ targets.T).argmax(1) == labels).float().mean().item()
    print(f"overfit accuracy over {len(labels)} Gaussians: {accuracy:.4f}")
    assert accuracy >= 0.95
