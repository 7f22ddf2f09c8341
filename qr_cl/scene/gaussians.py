"""The Gaussian type of the renderer, the scene files and the network: activated 3D Gaussians, and
quaternion math. The functions here take numpy arrays and torch tensors alike."""
from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
import torch

from ..runtime.constants import SH_C0

#: A numpy array or a torch tensor (the functions and the Gaussians here take both).
Array = np.ndarray | torch.Tensor

#: Quaternions whose norm is within this of 1 are unit to float32 rounding and kept as they are.
_UNIT_TOLERANCE = 1e-6


class SceneFormatError(ValueError):
    """A scene file is malformed; the message names the file and the problem."""


@dataclass(frozen=True, eq=False)
class Gaussians:
    """Activated 3D Gaussians (N of them): float32 arrays, all numpy (the renderer and the scene
    files) or all torch tensors (the network); :meth:`to_torch` and :meth:`to_numpy` convert
    without copying.

    - ``means`` [N,3]: centres, world units (metres when the scene is metric).
    - ``quats`` [N,4]: rotations, w,x,y,z; must be non-zero, normalized here.
    - ``scales`` [N,3]: activated (exp'd) standard deviations along the principal axes, world
      units, >= 0.
    - ``opacities`` [N]: activated (sigmoid'd) opacities in [0, 1].
    - ``sh`` [N,(d+1)^2,3]: spherical-harmonic coefficients of degree d <= 3, coefficient-major;
      ``sh[:, 0]`` is the DC term (:attr:`rgb`), ``sh[:, 1:]`` the higher bands (:attr:`sh_rest`).

    Raises TypeError for a field that is not an array of the kind of ``means``, and ValueError
    naming the field for a wrong shape or dtype, a NaN/inf, negative scales, opacities outside
    [0, 1] or a zero quaternion. Quaternions whose norm is off 1 by more than 1e-6 are normalized;
    the others (unit to float32 rounding), and all other fields, are kept without a copy.
    """

    means: Array
    quats: Array
    scales: Array
    opacities: Array
    sh: Array

    def __post_init__(self) -> None:
        _check("means", self.means, ("N", 3))
        n = self.means.shape[0]
        for name, shape in (("quats", (n, 4)), ("scales", (n, 3)), ("opacities", (n,)),
                            ("sh", (n, "(d+1)^2", 3))):
            _check(name, getattr(self, name), shape, like=self.means)
        if self.sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"sh must have shape [N, (d+1)^2, 3] with SH degree d <= 3, got {list(self.sh.shape)}")
        if bool((self.scales < 0).any()):
            raise ValueError("scales must be activated (>= 0); got negative values (pass exp(log_scale))")
        if bool(((self.opacities < 0) | (self.opacities > 1)).any()):
            raise ValueError("opacities must be activated, in [0, 1] (pass sigmoid(logit))")
        norms = ((self.quats ** 2).sum(-1)) ** 0.5
        if bool((norms == 0).any()):
            raise ValueError("quats contain zero quaternions")
        off_unit = abs(norms - 1) > _UNIT_TOLERANCE
        if bool(off_unit.any()):
            xp = _namespace(self.quats)
            object.__setattr__(self, "quats", xp.where(off_unit[:, None], self.quats / norms[:, None], self.quats))

    @classmethod
    def from_rgb(cls, means: Array, quats: Array, scales: Array, opacities: Array, rgb: Array,
                 sh_rest: Array | None = None) -> Gaussians:
        """Gaussians whose DC term gives the colour ``rgb`` [N,3] (>= 0; any floating dtype):
        ``sh[:, 0] = (rgb - 0.5) / SH_C0``, computed in float64 and stored as float32. ``sh_rest``
        [N,(d+1)^2-1,3] float32 are the higher bands (None for degree 0). The other fields are as
        in :class:`Gaussians`."""
        _check("rgb", rgb, (len(means), 3), float32=False)
        dc = _astype((_astype(rgb, "float64") - 0.5) / SH_C0, "float32")[:, None, :]
        if sh_rest is None:
            return cls(means, quats, scales, opacities, dc)
        _check("sh_rest", sh_rest, (len(means), "(d+1)^2-1", 3), like=rgb)
        return cls(means, quats, scales, opacities, _namespace(rgb).concatenate([dc, sh_rest], 1))

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        """The SH degree d (0..3) of :attr:`sh`."""
        return math.isqrt(self.sh.shape[1]) - 1

    @property
    def rgb(self) -> Array:
        """[N,3] view-independent colour from the DC term, ``max(0, 0.5 + SH_C0 * sh[:, 0])``."""
        return rgb_from_sh_dc(self.sh[:, 0])

    @property
    def sh_rest(self) -> Array:
        """[N,(d+1)^2-1,3] SH coefficients of the bands >= 1 (a view of :attr:`sh`; [N,0,3] for d = 0)."""
        return self.sh[:, 1:]

    def rotations(self) -> Array:
        """Rotation matrices [N,3,3] (columns are the principal axes)."""
        return quat_to_rotmat(self.quats)

    def axis_sigmas(self) -> Array:
        """Standard deviations [N,3] along world x, y, z: ``sqrt(diag(R S^2 R^T))``, world units."""
        return (((self.rotations() * self.scales[:, None, :]) ** 2).sum(-1)) ** 0.5

    def to_torch(self) -> Gaussians:
        """These Gaussians as torch tensors sharing memory with the numpy arrays (self when they
        are tensors already)."""
        if isinstance(self.means, torch.Tensor):
            return self
        return Gaussians(*(torch.from_numpy(a) for a in self._arrays()))

    def to_numpy(self) -> Gaussians:
        """These Gaussians as numpy arrays, sharing memory with CPU tensors (self when they are
        numpy arrays already)."""
        if isinstance(self.means, np.ndarray):
            return self
        return Gaussians(*(a.detach().cpu().numpy() for a in self._arrays()))

    def subset(self, index: Array) -> Gaussians:
        """The Gaussians selected by a boolean mask or an index array."""
        return Gaussians(*(a[index] for a in self._arrays()))

    def transformed(self, scale: float = 1.0, quat_wxyz=(1.0, 0.0, 0.0, 0.0),
                    translation=(0.0, 0.0, 0.0)) -> Gaussians:
        """A copy, as numpy arrays, under the similarity x -> R(quat) * scale * x + translation.

        SH coefficients are left unrotated (exact for degree 0).
        """
        g = self.to_numpy()
        q = np.asarray(quat_wxyz, np.float64)
        rot = quat_to_rotmat(q[None] / np.linalg.norm(q))[0]
        means = (scale * g.means.astype(np.float64)) @ rot.T + np.asarray(translation)
        quats = quat_multiply(np.broadcast_to(q / np.linalg.norm(q), g.quats.shape), g.quats)
        return replace(g, means=means.astype(np.float32), quats=quats.astype(np.float32),
                       scales=(g.scales * scale).astype(np.float32))

    def _arrays(self) -> list[Array]:
        return [getattr(self, f.name) for f in fields(self)]


def rgb_from_sh_dc(dc: Array) -> Array:
    """View-independent colour [N,3] in [0, inf) from SH DC coefficients [N,3]:
    ``max(0, 0.5 + SH_C0 * dc)``.

    This is also the colour averaged over all view directions when higher SH bands are present
    (they integrate to zero over the sphere).
    """
    return (0.5 + SH_C0 * dc).clip(min=0.0)


def quat_to_rotmat(q: Array) -> Array:
    """Rotation matrices [...,3,3] from unit w,x,y,z quaternions [...,4]."""
    w, x, y, z = (q[..., i] for i in range(4))
    return _namespace(q).stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(*q.shape[:-1], 3, 3)


def quat_multiply(a: Array, b: Array) -> Array:
    """Hamilton products a*b of w,x,y,z quaternions [N,4]."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return _namespace(a).stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)


def _namespace(a: Array):
    """The module of ``a``'s kind: torch for a tensor, numpy otherwise."""
    return torch if isinstance(a, torch.Tensor) else np


def _astype(a: Array, dtype: str) -> Array:
    """``a`` converted to ``dtype`` ('float32' or 'float64'), numpy or torch alike."""
    return a.to(getattr(torch, dtype)) if isinstance(a, torch.Tensor) else a.astype(dtype)


def _check(name: str, a: object, shape: tuple[int | str, ...], like: Array | None = None, float32: bool = True) -> None:
    """Raise TypeError unless ``a`` is an array (of the kind of ``like`` when given), ValueError
    naming ``name`` unless it has ``shape`` (strings name free sizes), a floating dtype (float32
    when ``float32``) and only finite values."""
    if not isinstance(a, (np.ndarray, torch.Tensor)):
        raise TypeError(f"{name} must be a numpy array or a torch tensor, got {type(a).__name__}")
    if like is not None and isinstance(a, torch.Tensor) != isinstance(like, torch.Tensor):
        raise TypeError(f"{name} is a {type(a).__name__}, the other fields are {type(like).__name__}s: "
                        "use numpy arrays or torch tensors for all")
    if a.ndim != len(shape) or any(isinstance(s, int) and s != d for s, d in zip(shape, a.shape)):
        raise ValueError(f"{name} must have shape [{', '.join(str(s) for s in shape)}], got {list(a.shape)}")
    is_tensor = isinstance(a, torch.Tensor)
    if not (a.dtype.is_floating_point if is_tensor else np.issubdtype(a.dtype, np.floating)):
        raise ValueError(f"{name} must be a floating-point array, got {a.dtype}")
    if float32 and a.dtype != (torch.float32 if is_tensor else np.float32):
        raise ValueError(f"{name} must be float32, got {a.dtype}")
    if not bool(_namespace(a).isfinite(a).all()):
        raise ValueError(f"{name} contains NaN or infinite values")
