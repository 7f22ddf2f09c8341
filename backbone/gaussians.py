"""Activated 3D Gaussians as the network's input, with validation and geometry helpers."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

#: Degree-0 spherical-harmonics constant (3DGS ``SH_C0``).
SH_C0 = 0.28209479177387814


def rgb_from_sh_dc(f_dc: Tensor) -> Tensor:
    """View-independent colour ``[N, 3]`` in [0, inf) from SH DC coefficients ``[N, 3]``: ``max(0, 0.5 + SH_C0 * f_dc)``.

    This is also the colour averaged over all view directions when higher SH bands are present
    (they integrate to zero over the sphere).
    """
    return (0.5 + SH_C0 * f_dc).clamp_min(0.0)


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices ``[N, 3, 3]`` from unit quaternions ``[N, 4]`` (w, x, y, z)."""
    w, x, y, z = quats.unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*quats.shape[:-1], 3, 3)


def _check(name: str, t: Tensor, shape: tuple[int | None, ...]) -> None:
    if not isinstance(t, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(t).__name__}")
    if t.dim() != len(shape) or any(s is not None and s != d for s, d in zip(shape, t.shape)):
        want = "[" + ", ".join("N" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must have shape {want}, got {list(t.shape)}")
    if not t.dtype.is_floating_point:
        raise ValueError(f"{name} must be a floating-point tensor, got {t.dtype}")
    if not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} contains NaN or infinite values")


@dataclass(frozen=True)
class GaussianSet:
    """One scene's activated Gaussians (N of them).

    - ``means`` ``[N, 3]``: centres, scene units (metres when the scene is metric).
    - ``quats`` ``[N, 4]``: rotations (w, x, y, z); normalized here, must be non-zero.
    - ``scales`` ``[N, 3]``: activated (exp'd) standard deviations, scene units, >= 0.
    - ``opacities`` ``[N]``: activated (sigmoid'd) opacities in [0, 1].
    - ``rgb`` ``[N, 3]``: colour, e.g. :func:`rgb_from_sh_dc`.
    - ``sh_rest`` ``[N, R, 3]`` or None: SH coefficients of bands >= 1 (R = (degree + 1)^2 - 1),
      coefficient-major, used as extra input features when the voxel config asks for them.

    Raises ValueError naming the field on a wrong shape, a NaN/inf, or an out-of-range value.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    rgb: Tensor
    sh_rest: Tensor | None = None

    def __post_init__(self) -> None:
        _check("means", self.means, (None, 3))
        n = self.means.shape[0]
        _check("quats", self.quats, (n, 4))
        _check("scales", self.scales, (n, 3))
        _check("opacities", self.opacities, (n,))
        _check("rgb", self.rgb, (n, 3))
        if self.sh_rest is not None:
            _check("sh_rest", self.sh_rest, (n, None, 3))
        if n and bool((self.scales < 0).any()):
            raise ValueError("scales must be activated (>= 0); got negative values (pass exp(log_scale))")
        if n and bool(((self.opacities < 0) | (self.opacities > 1)).any()):
            raise ValueError("opacities must be activated, in [0, 1] (pass sigmoid(logit))")
        norms = self.quats.norm(dim=1, keepdim=True)
        if n and bool((norms == 0).any()):
            raise ValueError("quats contain zero quaternions")
        object.__setattr__(self, "quats", self.quats / norms)

    @classmethod
    def from_sh(cls, means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, sh: Tensor) -> GaussianSet:
        """Build from SH coefficients ``sh`` ``[N, (d+1)^2, 3]`` (DC first): rgb from the DC term, the rest kept."""
        _check("sh", sh, (means.shape[0], None, 3))
        if sh.shape[1] < 1:
            raise ValueError("sh must hold at least the DC coefficient")
        rest = sh[:, 1:] if sh.shape[1] > 1 else None
        return cls(means, quats, scales, opacities, rgb_from_sh_dc(sh[:, 0]), rest)

    def __len__(self) -> int:
        return self.means.shape[0]

    def rotations(self) -> Tensor:
        """Rotation matrices ``[N, 3, 3]`` (columns are the Gaussian's principal axes)."""
        return quat_to_rotmat(self.quats)

    def axis_sigmas(self) -> Tensor:
        """Standard deviation along x, y, z ``[N, 3]``: ``sqrt(diag(R S^2 R^T))``, scene units."""
        r = self.rotations()
        return torch.sqrt(((r * self.scales[:, None, :]) ** 2).sum(-1))
