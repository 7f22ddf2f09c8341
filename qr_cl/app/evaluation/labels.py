"""Ground truth of open-vocabulary segmentation per Gaussian: per-Gaussian labels, or pseudo labels
from a labelled point cloud (paper App. B); and the Gaussians a view's rays can reach.
Gaussians with opacity < :data:`MIN_OPACITY` get label -1 (ignored by the evaluation)."""
from __future__ import annotations

import numpy as np

from ...runtime import DEFAULTS
from ...scene import Gaussians, quat_to_rotmat
from ...render import ray_entries, select_rays
from ..scenes.folders import SceneData
from ..training.rays import view_plan

MIN_OPACITY = 0.1


def pseudo_labels(gaussians: Gaussians, points: np.ndarray, labels: np.ndarray, k: int = 5,
                  max_mahalanobis: float = 0.1, min_opacity: float = MIN_OPACITY) -> np.ndarray:
    """Per-Gaussian labels [N] int64 from a labelled point cloud (paper App. B); -1 = no label.

    points [P,3] (scene units), labels [P]. For each Gaussian: its ``k`` nearest points (open3d
    KD-tree, Euclidean), majority label (ties go to the nearer point). Dropped (-1): opacity <
    ``min_opacity``, or every neighbour farther than ``max_mahalanobis`` in the Gaussian's own
    Mahalanobis distance sqrt(d^T Sigma^-1 d), Sigma = R S^2 R^T.
    """
    n = len(gaussians)
    if len(points) == 0:
        return np.full(n, -1, np.int64)
    import open3d as o3d  # function-local: open3d is slow to import and only the pseudo labels need it
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    tree = o3d.geometry.KDTreeFlann(cloud)
    k = min(k, len(points))
    idx = np.empty((n, k), np.int64)
    for i, m in enumerate(np.asarray(gaussians.means, np.float64)):
        idx[i] = np.asarray(tree.search_knn_vector_3d(m, k)[1])
    d = np.asarray(points)[idx] - gaussians.means[:, None, :].astype(np.float64)          # [N,k,3]
    rot = quat_to_rotmat(gaussians.quats.astype(np.float64))                               # [N,3,3]
    local = np.einsum("nji,nkj->nki", rot, d) / np.maximum(gaussians.scales[:, None, :], 1e-12)
    maha = np.linalg.norm(local, axis=2)                                                   # [N,k]
    lab = np.asarray(labels, np.int64)[idx]
    votes = (lab[:, :, None] == lab[:, None, :]).sum(2)
    out = lab[np.arange(n), votes.argmax(1)]
    out[(maha > max_mahalanobis).all(1) | (gaussians.opacities < min_opacity)] = -1
    return out


def ground_truth(scene: SceneData, source: str = "auto", k: int = 5, max_mahalanobis: float = 0.1) -> tuple[np.ndarray, str]:
    """(labels [N] int64 with -1 = ignored, the source used). ``source``: "points" (App. B from
    labels/points.ply), "gaussians" (labels/gaussian_labels.npy) or "auto" (points when present)."""
    if source not in ("auto", "points", "gaussians"):
        raise ValueError(f"ground truth source {source!r}: choose auto, points or gaussians")
    if source in ("auto", "points") and scene.points is not None:
        return pseudo_labels(scene.gaussians, scene.points, scene.point_labels, k, max_mahalanobis), "points"
    if source in ("auto", "gaussians") and scene.gaussian_labels is not None:
        labels = scene.gaussian_labels.copy()
        labels[scene.gaussians.opacities < MIN_OPACITY] = -1
        return labels, "gaussians"
    raise ValueError(f"{scene.root}: no ground truth for source={source!r} (labels/points.ply or "
                     "labels/gaussian_labels.npy)")


def reached_gaussians(scene: SceneData, sampler: str = DEFAULTS.sampler, k: int = DEFAULTS.k) -> np.ndarray:
    """[N] bool: the Gaussians that ``sampler``'s selection (``k``) of some pixel of some view of
    ``scene`` holds, i.e. those its training rays can reach. A per-scene model (the free-feature
    fit) learns only these; GS-Net predicts every Gaussian from its neighbourhood."""
    reached = np.zeros(len(scene.gaussians), bool)
    for view in range(len(scene.frames)):
        sel = select_rays(view_plan(scene, view), sampler, k)
        reached[sel.ids.get()[ray_entries(*sel.spans())]] = True
    return reached
