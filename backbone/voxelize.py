"""Voxelization of Gaussians into sparse voxels and de-voxelization back (paper App. F).

Each Gaussian contributes one or more *samples* (a sample is a (Gaussian, voxel) pair):
``center`` samples the voxel holding its mean; ``volume`` samples every voxel that its 3-sigma
axis-aligned box overlaps, with the opacity attenuated by ``exp(-0.5 * mahalanobis^2)`` at the
voxel centre. Samples falling in the same voxel are merged into one unique voxel; the inverse
index (sample -> voxel) and the count of samples per Gaussian are kept for de-voxelization.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Sequence

import torch
from torch import Tensor

from qr_cl.scene import Gaussians
from .sparse import MAX_BATCH, KernelMapCache, pack_keys, unpack_keys

SampleShape = Literal["center", "volume"]
Reduce = Literal["max", "mean"]

_WEIGHT_EPS = 1e-6
_MAX_OPACITY = 1.0 - 1e-6


@dataclass(frozen=True)
class VoxelConfig:
    """How Gaussians become voxel inputs.

    - ``grid_size``: voxel edge, scene units (0.05 = 5 cm in a metric scene, the paper's best).
    - ``sample_shape``: ``center`` (one voxel per Gaussian) or ``volume`` (its 3-sigma box).
    - ``max_extent``: volume sampling keeps at most this many voxels on each side of the voxel
      holding the mean, per axis (bounds the cost of huge Gaussians).
    - ``max_samples``: volume sampling raises ValueError, before allocating, when one scene would
      make more samples than this (each costs a few hundred bytes of temporaries).
    - ``use_scale`` / ``use_rotation``: append ``log(scale / grid_size)`` (3) and the quaternion
      with ``w >= 0`` (4) to the voxel features.
    - ``sh_rest_coeffs``: number of SH coefficients beyond DC to append (x3 channels), e.g. 3 for
      degree 1, 15 for degree 3; 0 uses RGB only.
    """

    grid_size: float = 0.05
    sample_shape: SampleShape = "center"
    max_extent: int = 4
    max_samples: int = 10_000_000
    use_scale: bool = False
    use_rotation: bool = False
    sh_rest_coeffs: int = 0

    def __post_init__(self) -> None:
        if not (self.grid_size > 0):
            raise ValueError(f"grid_size must be > 0, got {self.grid_size}")
        if self.sample_shape not in ("center", "volume"):
            raise ValueError(f"sample_shape must be 'center' or 'volume', got {self.sample_shape!r}")
        if self.max_extent < 0:
            raise ValueError(f"max_extent must be >= 0, got {self.max_extent}")
        if self.max_samples < 1:
            raise ValueError(f"max_samples must be >= 1, got {self.max_samples}")
        if self.sh_rest_coeffs < 0:
            raise ValueError(f"sh_rest_coeffs must be >= 0, got {self.sh_rest_coeffs}")

    @property
    def num_features(self) -> int:
        """Channels of a voxel feature: offset (3), rgb (3), opacity (1) and the optional ones."""
        return 7 + 3 * self.use_scale + 4 * self.use_rotation + 3 * self.sh_rest_coeffs


@dataclass
class VoxelBatch:
    """Unique voxels of one or more scenes, and the way back to their Gaussians.

    - ``coords`` ``[M, 4]`` int64: (scene index, i, j, k) voxel indices, each scene shifted so
      that its smallest occupied index per axis is 0; key-sorted, unique.
    - ``feats`` ``[M, F]`` float32: aggregated voxel inputs (see :func:`voxelize`).
    - ``sample_voxel`` ``[S]`` int64: the voxel of each sample (the inverse index).
    - ``sample_gaussian`` ``[S]`` int64: the Gaussian of each sample (index into the concatenated
      Gaussians of all scenes), non-decreasing.
    - ``samples_per_gaussian`` ``[N]`` int64: samples of each Gaussian (>= 1).
    - ``gaussians_per_scene``: N of each scene, in batch order.
    - ``cache``: kernel maps of these coordinates, filled by the first forward and reused after.
    """

    coords: Tensor
    feats: Tensor
    sample_voxel: Tensor
    sample_gaussian: Tensor
    samples_per_gaussian: Tensor
    gaussians_per_scene: tuple[int, ...]
    grid_size: float
    cache: KernelMapCache = field(default_factory=KernelMapCache, repr=False)

    @property
    def num_gaussians(self) -> int:
        """Total Gaussians over all scenes."""
        return self.samples_per_gaussian.shape[0]

    @property
    def one_sample_per_gaussian(self) -> bool:
        """True when every Gaussian has exactly one sample (``center`` sampling)."""
        return self.sample_voxel.shape[0] == self.num_gaussians

    def split(self, per_gaussian: Tensor) -> tuple[Tensor, ...]:
        """Split a per-Gaussian tensor ``[N, ...]`` into one tensor per scene."""
        return torch.split(per_gaussian, list(self.gaussians_per_scene))


def _samples(g: Gaussians, config: VoxelConfig) -> tuple[Tensor, Tensor, Tensor]:
    """Samples of one scene (torch storage): Gaussian index ``[S]``, voxel index ``[S, 3]`` int64, opacity ``[S]``."""
    grid = config.grid_size
    means = g.means
    home = torch.floor(means / grid).to(torch.int64)
    n = len(g)
    if config.sample_shape == "center":
        return torch.arange(n), home, g.opacities
    reach = 3.0 * g.axis_sigmas()
    lo = torch.maximum(torch.floor((means - reach) / grid).to(torch.int64), home - config.max_extent)
    hi = torch.minimum(torch.floor((means + reach) / grid).to(torch.int64), home + config.max_extent)
    extent = hi - lo + 1
    counts = extent.prod(dim=1)
    total = int(counts.sum())
    if total > config.max_samples:
        raise ValueError(
            f"volume sampling would make {total} samples for {n} Gaussians (max_samples={config.max_samples}): "
            "use a larger grid_size, a smaller max_extent, or raise max_samples"
        )
    gid = torch.repeat_interleave(torch.arange(n), counts)
    first = torch.cumsum(counts, 0) - counts
    local = torch.arange(gid.shape[0]) - first[gid]
    ext = extent[gid]
    step = torch.stack([local // (ext[:, 1] * ext[:, 2]), (local // ext[:, 2]) % ext[:, 1], local % ext[:, 2]], 1)
    voxel = lo[gid] + step
    diff = (voxel.float() + 0.5) * grid - means[gid]
    local_axes = torch.einsum("sij,si->sj", g.rotations()[gid], diff)
    maha2 = ((local_axes / g.scales[gid].clamp_min(1e-12)) ** 2).sum(1)
    return gid, voxel, g.opacities[gid] * torch.exp(-0.5 * maha2)


def _sample_features(g: Gaussians, gid: Tensor, voxel: Tensor, config: VoxelConfig) -> Tensor:
    """Per-sample features except opacity ``[S, F - 1]`` (torch storage): offset, rgb, then the optional ones."""
    grid = config.grid_size
    offset = g.means[gid] / grid - (voxel.float() + 0.5)
    parts = [offset, g.rgb[gid]]
    if config.use_scale:
        parts.append(torch.log(g.scales.clamp_min(1e-12) / grid)[gid])
    if config.use_rotation:
        q = g.quats
        parts.append(torch.where(q[:, :1] < 0, -q, q)[gid])
    if config.sh_rest_coeffs:
        have = g.sh_rest.shape[1]
        if have < config.sh_rest_coeffs:
            raise ValueError(f"the config uses {config.sh_rest_coeffs} SH rest coefficients, the Gaussians have {have}")
        parts.append(g.sh_rest[:, : config.sh_rest_coeffs].reshape(len(g), -1)[gid])
    return torch.cat(parts, 1)


def voxelize(scenes: Gaussians | Sequence[Gaussians], config: VoxelConfig = VoxelConfig()) -> VoxelBatch:
    """Voxelize one or more scenes (scene b gets batch index b) into a :class:`VoxelBatch`.

    Each scene is a :class:`qr_cl.scene.Gaussians`, numpy or torch storage (numpy arrays are
    viewed as tensors without a copy); the Gaussians validated their fields on construction.

    Voxel features ``[M, config.num_features]``, in this order:
    offset of the Gaussian mean from the voxel centre in voxel units (3; in [-0.5, 0.5) for
    ``center`` samples), rgb (3), opacity (1), then ``log(scale / grid_size)`` (3), the
    quaternion with w >= 0 (4) and SH rest coefficients (3 each) when configured. Samples sharing
    a voxel are merged by a mean weighted by sample opacity (+1e-6), except opacity, which becomes
    the union ``1 - prod(1 - o)``.
    """
    scenes = [g.to_torch() for g in ([scenes] if isinstance(scenes, Gaussians) else scenes)]
    if len(scenes) > MAX_BATCH:
        raise ValueError(f"at most {MAX_BATCH} scenes per batch, got {len(scenes)}")
    keys, gids, opac, feats = [], [], [], []
    base = 0
    for b, g in enumerate(scenes):
        gid, voxel, o = _samples(g, config)
        feats.append(_sample_features(g, gid, voxel, config))
        if voxel.shape[0]:
            voxel = voxel - voxel.min(0).values
        keys.append(pack_keys(torch.cat([torch.full_like(voxel[:, :1], b), voxel], 1)))
        gids.append(gid + base)
        opac.append(o)
        base += len(g)
    sample_keys = torch.cat(keys)
    sample_gaussian = torch.cat(gids)
    o = torch.cat(opac).clamp(0.0, _MAX_OPACITY)
    f = torch.cat(feats)
    unique_keys, sample_voxel = torch.unique(sample_keys, return_inverse=True)
    m = unique_keys.shape[0]
    w = o + _WEIGHT_EPS
    wsum = torch.zeros(m).index_add_(0, sample_voxel, w)
    merged = torch.zeros(m, f.shape[1]).index_add_(0, sample_voxel, f * w[:, None]) / wsum[:, None]
    union = 1.0 - torch.exp(torch.zeros(m).index_add_(0, sample_voxel, torch.log1p(-o)))
    voxel_feats = torch.cat([merged[:, :6], union[:, None], merged[:, 6:]], 1)
    return VoxelBatch(
        coords=unpack_keys(unique_keys),
        feats=voxel_feats,
        sample_voxel=sample_voxel,
        sample_gaussian=sample_gaussian,
        samples_per_gaussian=torch.bincount(sample_gaussian, minlength=base),
        gaussians_per_scene=tuple(len(g) for g in scenes),
        grid_size=config.grid_size,
    )


def devoxelize(voxel_feats: Tensor, batch: VoxelBatch, reduce: Reduce = "max", rows: Tensor | None = None) -> Tensor:
    """Voxel features ``[M, C]`` -> Gaussian features ``[N, C]``, or ``[len(rows), C]`` for the
    Gaussians ``rows`` (int64 indices into the batch's Gaussians, any order) only.

    Each sample takes its voxel's feature; a Gaussian's samples are reduced by ``max``
    (elementwise) or ``mean``. Gaussians sharing a voxel under ``center`` sampling get equal rows.
    With ``rows`` only those Gaussians' samples are gathered (cost proportional to them, not to N).
    """
    if voxel_feats.dim() != 2 or voxel_feats.shape[0] != batch.coords.shape[0]:
        raise ValueError(f"voxel_feats must have shape [{batch.coords.shape[0]}, C], got {list(voxel_feats.shape)}")
    if reduce not in ("max", "mean"):
        raise ValueError(f"reduce must be 'max' or 'mean', got {reduce!r}")
    if rows is not None:
        return _devoxelize_rows(voxel_feats, batch, reduce, rows)
    per_sample = voxel_feats.index_select(0, batch.sample_voxel)
    if batch.one_sample_per_gaussian:
        return per_sample
    out = voxel_feats.new_zeros(batch.num_gaussians, voxel_feats.shape[1])
    index = batch.sample_gaussian[:, None].expand_as(per_sample)
    return out.scatter_reduce(0, index, per_sample, "amax" if reduce == "max" else "mean", include_self=False)


def _devoxelize_rows(voxel_feats: Tensor, batch: VoxelBatch, reduce: Reduce, rows: Tensor) -> Tensor:
    """:func:`devoxelize` of the Gaussians ``rows`` [U]: [U, C]."""
    rows = torch.as_tensor(rows, dtype=torch.int64)
    if rows.dim() != 1 or (rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= batch.num_gaussians)):
        raise ValueError(f"rows must be a 1-D index into the batch's {batch.num_gaussians} Gaussians")
    if batch.one_sample_per_gaussian:        # sample g is Gaussian g
        return voxel_feats.index_select(0, batch.sample_voxel.index_select(0, rows))
    counts = batch.samples_per_gaussian.index_select(0, rows)
    first = (torch.cumsum(batch.samples_per_gaussian, 0) - batch.samples_per_gaussian).index_select(0, rows)
    local = torch.repeat_interleave(torch.arange(rows.shape[0]), counts)
    sample = first.index_select(0, local) + torch.arange(local.shape[0]) - (torch.cumsum(counts, 0) - counts)[local]
    per_sample = voxel_feats.index_select(0, batch.sample_voxel.index_select(0, sample))
    out = voxel_feats.new_zeros(rows.shape[0], voxel_feats.shape[1])
    index = local[:, None].expand_as(per_sample)
    return out.scatter_reduce(0, index, per_sample, "amax" if reduce == "max" else "mean", include_self=False)
