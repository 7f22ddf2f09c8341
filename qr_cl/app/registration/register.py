"""Dr.Splat's registration: CLIP features of the masks registered onto the Gaussians, no training.

Every pixel inside a mask gives its mask's feature to its top contributors
(:func:`~.contributors.top_contributors`: the K Gaussians with the largest V-Render weights
w = alpha_i T_i), weighted by w. A Gaussian's feature is the weighted sum over every view,
normalised to a unit row (the weighted mean's direction); Gaussians that no masked pixel picks get
a zero row, which the evaluation scores as unlabelled. Dr.Splat's product quantization is left out.

The weighted sum is the transpose of a blend (:func:`qr_cl.render.weighted_sums`:
dF[g] = sum over entries of w dImage[p]). dImage holds each pixel's mask as a one-hot row over the
view's masks (one column per mask of each level registered, and a last column of ones), so the
deterministic backward gives, per picked Gaussian, its weight sums per mask: [U, masks + 1] instead
of [U, C]; their product with the view's mask features [masks, C] adds the view's part to the
[N, C] sum. Views stream one at a time and each view's pixels in chunks of ``chunk_rays``: memory
is the [N, C] sum plus one chunk's selections, never per-view masks of the Gaussians (Dr.Splat's
visibility masks grow with the frame count). Twin: tests/app/register_twin.py.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from ...render import RasterPlan, listed_selection, weighted_sums
from ...scene import Camera, Gaussians
from ..scenes.folders import SceneData, unit_rows
from ..timing import Stopwatch
from ..training.rays import camera_plan
from .contributors import top_contributors

#: Dr.Splat's top-k contributors per pixel.
DRSPLAT_K = 40
#: Pixels registered per selection: bounds one step's memory whatever the image size (its V-Render
#: walks reach the host as [pixels, longest walk] arrays to find each pixel's top K).
CHUNK_RAYS = 1 << 14


@dataclass
class ViewMasks:
    """One view's masks: ``masks`` [L,H,W] int32, per registered level the row of ``features``
    [M,C] (float32 unit rows) of each pixel's mask, -1 where it has none."""

    name: str
    camera: Camera
    masks: np.ndarray
    features: np.ndarray


def scene_views(levels: list[SceneData]) -> Iterator[ViewMasks]:
    """The views of one scene folder loaded once per mask level to register (``levels``: e.g.
    ``[load_scene_folder(path, j) for j in (0, 1, 2, 3)]``, or one loading for the chosen level),
    each level's masks in its own rows of the view's stacked features."""
    first = levels[0]
    for i, frame in enumerate(first.frames):
        parts = [scene.frames[i] for scene in levels]
        starts = np.cumsum([0] + [len(p.features) for p in parts[:-1]])
        masks = np.stack([np.where(p.masks >= 0, p.masks + s, -1) for p, s in zip(parts, starts)]).astype(np.int32)
        yield ViewMasks(frame.name, frame.camera, masks, np.concatenate([p.features for p in parts]))


@dataclass
class Registration:
    """Registered features [N,C] float32 (unit rows; zero rows for the Gaussians no masked pixel
    picks), each Gaussian's total weight [N] float64 (sum of its alpha_i T_i over the masked pixels
    that pick it), K, and what it took: views, rays (masked pixels), entries (picks) and seconds."""

    features: np.ndarray
    weight: np.ndarray
    k: int
    views: int
    rays: int
    entries: int
    seconds: float

    @property
    def reached(self) -> np.ndarray:
        """[N] bool: the Gaussians that some masked pixel picks (the others keep no feature)."""
        return self.weight > 0

    def summary(self) -> dict:
        """The numbers of the registration (not the features): K, Gaussians, reached, views, rays,
        entries, seconds."""
        return {"k": self.k, "gaussians": len(self.weight), "reached": int(self.reached.sum()),
                "views": self.views, "rays": self.rays, "entries": self.entries, "seconds": self.seconds}


def mask_weight_sums(plan: RasterPlan, pixels: np.ndarray, ids: np.ndarray, weights: np.ndarray,
                     pixel_masks: np.ndarray, n_masks: int) -> tuple[np.ndarray, np.ndarray]:
    """Per Gaussian picked by the rays ``pixels`` [P,2] of ``plan`` (contributors ``ids`` [P,K],
    -1 padded, with ``weights`` [P,K]; each ray's mask at every level ``pixel_masks`` [P,L], -1 none,
    values below ``n_masks``): (rows [U] int64, the picked Gaussians ascending; sums [U, n_masks + 1]
    float32: column m the sum of the weights from pixels whose mask is m at some level, the last
    column from all the pixels), by the transpose of a blend over the picks."""
    valid = ids >= 0
    rows = np.unique(ids[valid]).astype(np.int64)
    channels = n_masks + 1
    if not len(rows):
        return rows, np.zeros((0, channels), np.float32)
    dimage = np.zeros((len(ids), channels), np.float32)
    for level in pixel_masks.T:
        hit = np.flatnonzero(level >= 0)
        np.add.at(dimage, (hit, level[hit]), 1.0)
    dimage[:, n_masks] = 1.0
    compact = np.where(valid, np.searchsorted(rows, np.maximum(ids, 0)), -1)
    sel = listed_selection(plan, pixels, compact, weights, n_rows=len(rows))
    return rows, weighted_sums(sel, dimage).numpy()


def register(gaussians: Gaussians, views: Iterable[ViewMasks], k: int = DRSPLAT_K, chunk_rays: int = CHUNK_RAYS,
             progress: bool = True, total: int | None = None) -> Registration:
    """Register the masks of ``views`` (streamed: one view in memory at a time; ``total`` views
    for the progress bar) onto ``gaussians`` through each masked pixel's ``k`` top contributors
    (module docstring). Returns the :class:`Registration`; ValueError if a view's masks do not
    match its camera or no view is given."""
    watch = Stopwatch()
    n = len(gaussians)
    total_f, weight = None, np.zeros(n, np.float64)
    n_views = n_rays = n_entries = 0
    for view in tqdm(views, total=total, desc="register", unit="view", disable=not progress):
        cam = view.camera
        if view.masks.ndim != 3 or view.masks.shape[1:] != (cam.height, cam.width):
            raise ValueError(f"view {view.name!r}: masks {view.masks.shape} do not match its {cam.width}x{cam.height} "
                             "camera ([levels, H, W] expected)")
        if total_f is None:
            total_f = np.zeros((n, view.features.shape[1]), np.float32)
        plan = camera_plan(gaussians, cam)
        ys, xs = np.nonzero((view.masks >= 0).any(0))
        pixels = np.stack([xs, ys], 1).astype(np.int32)
        for start in range(0, len(pixels), chunk_rays):
            chunk = pixels[start:start + chunk_rays]
            ids, w = top_contributors(plan, chunk, k)
            rows, sums = mask_weight_sums(plan, chunk, ids, w, view.masks[:, chunk[:, 1], chunk[:, 0]].T,
                                          len(view.features))
            total_f[rows] += sums[:, :-1] @ view.features
            weight[rows] += sums[:, -1]
            n_entries += int((ids >= 0).sum())
        n_views += 1
        n_rays += len(pixels)
    if total_f is None:
        raise ValueError("no views to register")
    return Registration(unit_rows(total_f), weight, k, n_views, n_rays, n_entries, watch.seconds)
