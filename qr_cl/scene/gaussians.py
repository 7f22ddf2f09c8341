"""The Gaussian type of the renderer and the network: activated 3D Gaussians, and quaternion math."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ..runtime.constants import SH_C0


class SceneFormatError(ValueError):
    """A scene file is malformed; the message names the file and the problem."""


@dataclass
class Gaussians:
    """Activated 3D Gaussians (float32 numpy arrays).

    means [N,3] world units; quats [N,4] unit w,x,y,z; scales [N,3] standard deviations in world
    units; opacities [N] in [0,1]; sh [N,(d+1)^2,3] spherical-harmonic coefficients (sh[:,0] is
    the DC term; RGB = max(0, SH_C0 * dc + 0.5) for degree 0).
    """

    means: np.ndarray
    quats: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    sh: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.means)
        shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,)}
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"Gaussians.{name} has shape {getattr(self, name).shape}, expected {shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 or \
                self.sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"Gaussians.sh has shape {self.sh.shape}, expected (N, (d+1)^2, 3), d<=3")

    def __len__(self) -> int:
        return len(self.means)

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    @property
    def rgb(self) -> np.ndarray:
        """[N,3] view-independent colour from the DC term, in [0, 1] after clamping at 0."""
        return np.maximum(SH_C0 * self.sh[:, 0] + 0.5, 0.0).astype(np.float32)

    def subset(self, index: np.ndarray) -> "Gaussians":
        """The Gaussians selected by a boolean mask or an index array."""
        return Gaussians(self.means[index], self.quats[index], self.scales[index],
                         self.opacities[index], self.sh[index])

    def transformed(self, scale: float = 1.0, quat_wxyz=(1.0, 0.0, 0.0, 0.0),
                    translation=(0.0, 0.0, 0.0)) -> "Gaussians":
        """A copy under the similarity x -> R(quat) * scale * x + translation.

        SH coefficients are left unrotated (exact for degree 0).
        """
        q = np.asarray(quat_wxyz, np.float64)
        rot = quat_to_rotmat(q[None] / np.linalg.norm(q))[0]
        means = (scale * self.means.astype(np.float64)) @ rot.T + np.asarray(translation)
        quats = quat_multiply(np.broadcast_to(q / np.linalg.norm(q), self.quats.shape), self.quats)
        return replace(self, means=means.astype(np.float32), quats=quats.astype(np.float32),
                       scales=(self.scales * scale).astype(np.float32))


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [N,3,3] from unit w,x,y,z quaternions [N,4]."""
    w, x, y, z = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    return np.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], axis=-1).reshape(-1, 3, 3)


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a*b of w,x,y,z quaternions [N,4]."""
    aw, ax, ay, az = a.T
    bw, bx, by, bz = b.T
    return np.stack([aw * bw - ax * bx - ay * by - az * bz, aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx, aw * bz + ax * by - ay * bx + az * bw], -1)
