"""Gaussian voxelization and de-voxelization of backbone.voxelize."""

import math

import pytest
import torch

from qr_cl.backbone.voxelize import VoxelConfig, devoxelize, voxelize
from qr_cl.runtime import SH_C0
from qr_cl.scene import Gaussians, quat_to_rotmat, rgb_from_sh_dc


def random_gaussians(
    n: int, seed: int, extent: float = 1.0, scale: float = 0.03, sh_rest: int = 0, low: float = -0.3
) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians.from_rgb(
        means=torch.rand(n, 3, generator=g) * extent + low,
        quats=torch.randn(n, 4, generator=g),
        scales=torch.rand(n, 3, generator=g) * scale + 1e-3,
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        rgb=torch.rand(n, 3, generator=g),
        sh_rest=torch.randn(n, sh_rest, 3, generator=g) if sh_rest else None,
    )


def one_gaussian(mean, scale, opacity=0.8, quat=(1.0, 0.0, 0.0, 0.0), rgb=(0.2, 0.4, 0.6)) -> Gaussians:
    return Gaussians.from_rgb(
        torch.tensor([mean], dtype=torch.float32),
        torch.tensor([quat]),
        torch.tensor([scale], dtype=torch.float32),
        torch.tensor([opacity]),
        torch.tensor([rgb]),
    )


def test_center_sampling_puts_each_gaussian_in_the_voxel_of_its_mean():
    g = random_gaussians(2000, seed=0)
    cfg = VoxelConfig(grid_size=0.1)
    batch = voxelize([g], cfg)
    home = torch.floor(g.means / 0.1).long()
    home -= home.min(0).values
    assert torch.equal(batch.samples_per_gaussian, torch.ones(2000, dtype=torch.int64))
    assert torch.equal(batch.coords[batch.sample_voxel, 1:], home)
    assert bool((batch.coords[:, 0] == 0).all())
    assert batch.coords.shape[0] == torch.unique(home, dim=0).shape[0]
    assert torch.unique(batch.coords, dim=0).shape[0] == batch.coords.shape[0]
    assert batch.feats.shape == (batch.coords.shape[0], cfg.num_features)
    offset = batch.feats[:, :3]
    assert bool((offset >= -0.5).all()) and bool((offset < 0.5).all())
    alone = torch.nonzero(torch.bincount(batch.sample_voxel) == 1).squeeze(1)
    gid = torch.nonzero(torch.isin(batch.sample_voxel, alone)).squeeze(1)
    vox = batch.sample_voxel[gid]
    torch.testing.assert_close(batch.feats[vox, :3], g.means[gid] / 0.1 - torch.floor(g.means[gid] / 0.1) - 0.5)
    torch.testing.assert_close(batch.feats[vox, 3:6], g.rgb[gid])
    torch.testing.assert_close(batch.feats[vox, 6], g.opacities[gid])


def test_gaussians_sharing_a_voxel_are_merged():
    means = torch.tensor([[0.01, 0.02, 0.03], [0.05, 0.06, 0.07], [0.5, 0.5, 0.5]])
    g = Gaussians.from_rgb(
        means, torch.tensor([[1.0, 0, 0, 0]] * 3), torch.full((3, 3), 0.01),
        torch.tensor([0.5, 0.25, 0.9]), torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]),
    )
    batch = voxelize([g], VoxelConfig(grid_size=0.1))
    assert batch.coords.shape[0] == 2
    assert batch.sample_voxel[0] == batch.sample_voxel[1] != batch.sample_voxel[2]
    f = batch.feats[batch.sample_voxel[0]]
    w = torch.tensor([0.5, 0.25]) + 1e-6
    torch.testing.assert_close(f[3:6], (w[:, None] * g.rgb[:2]).sum(0) / w.sum())
    torch.testing.assert_close(f[6], torch.tensor(1 - 0.5 * 0.75))


def test_volume_sampling_covers_the_three_sigma_box():
    grid, sigma = 0.1, 0.1
    g = one_gaussian([0.23, 0.41, 0.05], [sigma, sigma, sigma])
    batch = voxelize([g], VoxelConfig(grid_size=grid, sample_shape="volume"))
    lo = torch.floor((g.means[0] - 3 * sigma) / grid)
    hi = torch.floor((g.means[0] + 3 * sigma) / grid)
    assert int(batch.samples_per_gaussian[0]) == int((hi - lo + 1).prod())
    assert batch.coords.shape[0] == batch.sample_voxel.shape[0]
    centres = (batch.coords[:, 1:].float() + lo + 0.5) * grid
    expected = 0.8 * torch.exp(-0.5 * ((centres - g.means[0]) ** 2).sum(1) / sigma**2)
    torch.testing.assert_close(batch.feats[:, 6], expected)
    torch.testing.assert_close(batch.feats[:, :3], (g.means[0] - centres) / grid)


def test_volume_opacity_uses_the_mahalanobis_distance_of_a_rotated_gaussian():
    quat = torch.nn.functional.normalize(torch.tensor([0.9, 0.3, -0.2, 0.4]), dim=0)
    scale = torch.tensor([0.12, 0.04, 0.02])
    g = one_gaussian([0.5, 0.5, 0.5], scale.tolist(), quat=quat.tolist(), opacity=0.6)
    batch = voxelize([g], VoxelConfig(grid_size=0.05, sample_shape="volume", max_extent=10))
    r = quat_to_rotmat(quat[None])[0]
    cov = r @ torch.diag(scale**2) @ r.T
    sig = torch.sqrt(torch.diag(cov))
    lo = torch.floor((g.means[0] - 3 * sig) / 0.05)
    hi = torch.floor((g.means[0] + 3 * sig) / 0.05)
    assert int(batch.samples_per_gaussian[0]) == int((hi - lo + 1).prod())
    d = (batch.coords[:, 1:].float() + lo + 0.5) * 0.05 - g.means[0]
    maha2 = torch.einsum("si,ij,sj->s", d.double(), torch.linalg.inv(cov.double()), d.double())
    torch.testing.assert_close(batch.feats[:, 6], (0.6 * torch.exp(-0.5 * maha2)).float(), rtol=1e-4, atol=1e-6)


def test_volume_extent_and_sample_count_are_capped():
    g = one_gaussian([0.0, 0.05, 0.05], [5.0, 0.001, 0.001])
    batch = voxelize([g], VoxelConfig(grid_size=0.1, sample_shape="volume", max_extent=2))
    assert int(batch.samples_per_gaussian[0]) == 5
    assert batch.coords[:, 1].tolist() == [0, 1, 2, 3, 4]
    with pytest.raises(ValueError, match="would make 5 samples"):
        voxelize([g], VoxelConfig(grid_size=0.1, sample_shape="volume", max_extent=2, max_samples=4))


@pytest.mark.parametrize("reduce", ["max", "mean"])
def test_devoxelize_matches_a_loop(reduce):
    torch.manual_seed(0)
    g = random_gaussians(60, seed=1, scale=0.08)
    batch = voxelize([g], VoxelConfig(grid_size=0.1, sample_shape="volume"))
    assert bool((batch.samples_per_gaussian > 1).any())
    vf = torch.randn(batch.coords.shape[0], 5, dtype=torch.float64, requires_grad=True)
    out = devoxelize(vf, batch, reduce)
    for i in range(len(g)):
        rows = vf[batch.sample_voxel[batch.sample_gaussian == i]]
        want = rows.max(0).values if reduce == "max" else rows.mean(0)
        torch.testing.assert_close(out[i], want)
    probe = torch.randn(out.shape, dtype=torch.float64)
    (grad,) = torch.autograd.grad((out * probe).sum(), vf)
    ref = torch.zeros_like(vf)
    for i in range(len(g)):
        vox = batch.sample_voxel[batch.sample_gaussian == i]
        if reduce == "mean":
            ref.index_add_(0, vox, probe[i].expand(len(vox), -1) / len(vox))
        else:
            arg = vf[vox].argmax(0)
            ref[vox[arg], torch.arange(5)] += probe[i]
    torch.testing.assert_close(grad, ref)


def test_batched_scenes_get_their_own_batch_index():
    a, b = random_gaussians(300, seed=2), random_gaussians(200, seed=3)
    cfg = VoxelConfig(grid_size=0.1, use_scale=True, use_rotation=True)
    batch = voxelize([a, b], cfg)
    alone = voxelize([b], cfg)
    assert batch.gaussians_per_scene == (300, 200)
    assert torch.equal(batch.coords[batch.sample_voxel[300:], 0], torch.ones(200, dtype=torch.int64))
    mine = batch.coords[:, 0] == 1
    assert torch.equal(batch.coords[mine, 1:], alone.coords[:, 1:])
    torch.testing.assert_close(batch.feats[mine], alone.feats)
    parts = batch.split(torch.arange(500))
    assert [len(p) for p in parts] == [300, 200]


def test_optional_features():
    g = random_gaussians(100, seed=4, sh_rest=8, low=0.1)
    cfg = VoxelConfig(grid_size=10.0, use_scale=True, use_rotation=True, sh_rest_coeffs=3)
    assert cfg.num_features == 7 + 3 + 4 + 9
    batch = voxelize([g], cfg)
    assert batch.coords.shape[0] == 1 and batch.feats.shape == (1, cfg.num_features)
    w = g.opacities + 1e-6
    q = torch.where(g.quats[:, :1] < 0, -g.quats, g.quats)
    torch.testing.assert_close(batch.feats[0, 10:14], (w[:, None] * q).sum(0) / w.sum())
    torch.testing.assert_close(batch.feats[0, 7:10], (w[:, None] * torch.log(g.scales / 10.0)).sum(0) / w.sum())
    sh = g.sh_rest[:, :3].reshape(100, 9)
    torch.testing.assert_close(batch.feats[0, 14:], (w[:, None] * sh).sum(0) / w.sum())
    with pytest.raises(ValueError, match="SH rest"):
        voxelize([random_gaussians(5, seed=5)], cfg)


def test_sh_helpers():
    sh = torch.randn(7, 16, 3)
    g = Gaussians(torch.zeros(7, 3), torch.randn(7, 4), torch.ones(7, 3), torch.full((7,), 0.5), sh)
    torch.testing.assert_close(g.rgb, (0.5 + SH_C0 * sh[:, 0]).clamp_min(0))
    torch.testing.assert_close(rgb_from_sh_dc(torch.tensor([[-10.0, 0.0, 1.0]])), torch.tensor([[0.0, 0.5, 0.5 + SH_C0]]))
    assert torch.equal(g.sh_rest, sh[:, 1:])
    torch.testing.assert_close(g.quats.norm(dim=1), torch.ones(7))
    r = g.rotations()
    torch.testing.assert_close(r @ r.transpose(1, 2), torch.eye(3).expand(7, 3, 3), atol=1e-5, rtol=0)


def test_empty_scene():
    empty = Gaussians.from_rgb(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3))
    for shape in ("center", "volume"):
        batch = voxelize([empty, random_gaussians(10, seed=6)], VoxelConfig(grid_size=0.1, sample_shape=shape))
        assert batch.gaussians_per_scene == (0, 10)
        assert bool((batch.coords[:, 0] == 1).all())
        assert devoxelize(torch.zeros(batch.coords.shape[0], 2), batch).shape == (10, 2)


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("means", torch.tensor([[0.0, float("nan"), 0.0]]), "means contains NaN"),
        ("means", torch.zeros(1, 2), r"means must have shape \[N, 3\]"),
        ("quats", torch.zeros(1, 4), "zero quaternions"),
        ("quats", torch.ones(2, 4), r"quats must have shape \[1, 4\]"),
        ("scales", torch.tensor([[-1.0, 1.0, 1.0]]), "scales must be activated"),
        ("opacities", torch.tensor([1.5]), "opacities must be activated"),
        ("opacities", torch.tensor([float("inf")]), "opacities contains NaN"),
        ("rgb", torch.zeros(1, 3, dtype=torch.int64), "rgb must be a floating-point"),
    ],
)
def test_bad_gaussians_are_named(field, value, message):
    fields = dict(
        means=torch.zeros(1, 3), quats=torch.tensor([[1.0, 0, 0, 0]]), scales=torch.ones(1, 3),
        opacities=torch.tensor([0.5]), rgb=torch.zeros(1, 3),
    )
    fields[field] = value
    with pytest.raises(ValueError, match=message):
        Gaussians.from_rgb(**fields)


def test_bad_configs_and_inputs():
    with pytest.raises(ValueError, match="grid_size"):
        VoxelConfig(grid_size=0.0)
    with pytest.raises(ValueError, match="sample_shape"):
        VoxelConfig(sample_shape="tri-plane")
    batch = voxelize([random_gaussians(10, seed=7)], VoxelConfig(grid_size=math.pi / 10))
    with pytest.raises(ValueError, match="voxel_feats"):
        devoxelize(torch.zeros(batch.coords.shape[0] + 1, 3), batch)
    with pytest.raises(ValueError, match="reduce"):
        devoxelize(torch.zeros(batch.coords.shape[0], 3), batch, "sum")
