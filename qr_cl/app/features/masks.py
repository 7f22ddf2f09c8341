"""SAM's automatic masks at LangSplat's four levels.

A grid of single-point prompts covers the image and, with ``crop_layers`` = 1, each of 2x2
overlapping crops (its own SAM embedding). Each point gives SAM's three multimask outputs;
LangSplat's levels are all of them ("default") and each output alone ("s", "m", "l"). Per level,
as SAM's generator does: masks whose predicted IoU is <= ``pred_iou`` or whose stability (IoU
of the logits thresholded at +1 and -1) is < ``stability`` are dropped (the cheap tests first:
the IoU before the masks are upscaled, a bound of the stability before they are upsampled to
the crop's size, then only the pixels near a threshold upsampled, :mod:`.mask_upsampling`), so
are masks near a crop edge that is not an image edge; box NMS removes duplicates within a crop
(by predicted IoU) and between crops (preferring smaller crops); holes and islands smaller than
``min_area`` px are removed, and box NMS runs again preferring masks that needed no such change.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from scipy import ndimage

from .boxes import mask_boxes, near_crop_edge, nms
from .mask_upsampling import stable_masks
from .sam_model import Sam

#: LangSplat's mask levels, in the order of ``_s.npy``.
LEVELS = ("default", "s", "m", "l")
#: 8-connectivity of the small-region removal.
_EIGHT = np.ones((3, 3), bool)


@dataclass(frozen=True)
class MaskSettings:
    """The generator's settings; the defaults are LangSplat's (its ``preprocess.py``)."""

    points_per_side: int = 32
    points_per_batch: int = 64
    pred_iou: float = 0.7
    stability: float = 0.85
    stability_offset: float = 1.0
    box_nms: float = 0.7
    crop_layers: int = 1
    crop_nms: float = 0.7
    crop_overlap: float = 512 / 1500
    min_area: int = 100


@dataclass
class Masks:
    """Masks of one level: ``masks`` [n, H, W] bool, ``boxes`` [n, 4] (x0, y0, x1, y1 inclusive,
    image px), ``iou`` [n] predicted IoU, ``stability`` [n], ``crop_areas`` [n] px of the crop
    each came from."""

    masks: torch.Tensor
    boxes: torch.Tensor
    iou: torch.Tensor
    stability: torch.Tensor
    crop_areas: torch.Tensor

    def __len__(self) -> int:
        return len(self.masks)

    def take(self, index: torch.Tensor) -> "Masks":
        """The masks at ``index`` (indices or a bool mask), in that order."""
        return Masks(self.masks[index], self.boxes[index], self.iou[index], self.stability[index],
                     self.crop_areas[index])

    @staticmethod
    def cat(parts: list["Masks"], shape: tuple[int, int], device) -> "Masks":
        """The masks of ``parts`` one after another (an empty set of masks of ``shape`` when none)."""
        if not parts:
            z = torch.zeros(0, device=device)
            return Masks(torch.zeros(0, *shape, dtype=torch.bool, device=device), torch.zeros(0, 4, device=device), z, z, z)
        return Masks(*(torch.cat([getattr(p, f) for p in parts]) for f in
                       ("masks", "boxes", "iou", "stability", "crop_areas")))


def point_grid(n: int) -> np.ndarray:
    """[n*n, 2] (x, y) in (0, 1): the centres of an n x n grid of cells, row by row."""
    side = np.linspace(1 / (2 * n), 1 - 1 / (2 * n), n)
    return np.stack([np.tile(side, n), np.repeat(side, n)], 1)


def crop_boxes(height: int, width: int, layers: int, overlap: float) -> list[tuple[int, int, int, int]]:
    """(x0, y0, x1, y1) of the whole image then, per layer i >= 1, (2^i)^2 overlapping crops
    (column by column)."""
    boxes = [(0, 0, width, height)]
    short = min(height, width)
    for layer in range(1, layers + 1):
        per_side = 2 ** layer
        lap = int(overlap * short * (2 / per_side))
        cw = math.ceil((lap * (per_side - 1) + width) / per_side)
        ch = math.ceil((lap * (per_side - 1) + height) / per_side)
        for x0 in (int((cw - lap) * i) for i in range(per_side)):
            for y0 in (int((ch - lap) * i) for i in range(per_side)):
                boxes.append((x0, y0, min(x0 + cw, width), min(y0 + ch, height)))
    return boxes


def _paste(pieces: list[torch.Tensor], piece: torch.Tensor, row: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """``out`` [n, h, w] (a window of the masks being made) with mask i row ``row[i]`` of
    ``pieces[piece[i]]`` (each [m, h, w] bool): only the masks asked for are copied."""
    for p, masks in enumerate(pieces):
        here = (piece == p).nonzero()[:, 0]
        if len(here):
            out[here] = masks[row[here]]
    return out


def _crop_masks(sam: Sam, image: np.ndarray, crop: tuple[int, int, int, int], settings: MaskSettings,
                full: tuple[int, int]) -> list[Masks]:
    """Per level, the masks of one crop that pass the per-mask filters and the crop's box NMS,
    placed in the whole image. Each batch's masks stay where the filters made them until NMS has
    picked the ones to place: the rest are never copied."""
    x0, y0, x1, y1 = crop
    view = sam.embed(np.ascontiguousarray(image[y0:y1, x0:x1]))
    ch, cw = y1 - y0, x1 - x0
    points = point_grid(settings.points_per_side) * np.array([cw, ch])
    offset = torch.tensor([x0, y0, x0, y0], dtype=torch.float32, device=sam.device)
    pieces, rows, found = [], [], []
    for start in range(0, len(points), settings.points_per_batch):
        tokens, iou = view.decode(points[start:start + settings.points_per_batch])
        passing = iou > settings.pred_iou                                  # the IoU filter before any upsampling
        prompts = passing.any(1)
        low = view.low_masks(tokens.take(prompts)).flatten(0, 1)
        keep = passing[prompts].flatten()
        output = (torch.arange(len(keep), device=keep.device) % 3)[keep]
        low, iou = low[keep], iou[prompts].flatten()[keep]
        keep, masks, stab = stable_masks(low, view.rows, view.cols, settings.stability_offset, settings.stability)
        iou, output = iou[keep], output[keep]
        boxes = mask_boxes(masks) + offset
        keep = (~near_crop_edge(boxes, crop, (0, 0, full[1], full[0]))).nonzero()[:, 0]
        pieces.append(masks)
        rows.append(keep)
        found.append((boxes[keep], iou[keep], stab[keep], output[keep]))
    piece = torch.cat([torch.full_like(r, p) for p, r in enumerate(rows)])
    row = torch.cat(rows)
    boxes, iou, stab, output = (torch.cat(f) for f in zip(*found))
    result = []
    for sel in (None, 0, 1, 2):
        index = torch.arange(len(boxes), device=boxes.device) if sel is None else (output == sel).nonzero()[:, 0]
        index = index[nms(boxes[index], iou[index], settings.box_nms)]
        placed = torch.zeros(len(index), *full, dtype=torch.bool, device=sam.device)
        _paste(pieces, piece[index], row[index], placed[:, y0:y1, x0:x1])
        result.append(Masks(placed, boxes[index], iou[index], stab[index],
                            torch.full((len(index),), float(cw * ch), device=boxes.device)))
    return result


def remove_small_regions(mask: np.ndarray, min_area: int, holes: bool) -> tuple[np.ndarray, bool]:
    """(``mask`` [H, W] bool without its holes (``holes``) or islands smaller than ``min_area``
    px (8-connected; the largest island stays when all are small), whether it changed)."""
    regions, count = ndimage.label(~mask if holes else mask, structure=_EIGHT)
    sizes = np.bincount(regions.ravel(), minlength=count + 1)[1:]
    small = np.flatnonzero(sizes < min_area) + 1
    if len(small) == 0:
        return mask, False
    if holes:
        return mask | np.isin(regions, small), True
    big = np.setdiff1d(np.arange(1, count + 1), small)
    return np.isin(regions, big if len(big) else [int(np.argmax(sizes)) + 1]), True


def _clean(level: Masks, settings: MaskSettings) -> Masks:
    """Small holes and islands removed, then box NMS preferring unchanged masks."""
    if len(level) == 0 or settings.min_area <= 0:
        return level
    cleaned, unchanged = [], []
    for mask in level.masks.cpu().numpy():
        mask, changed_holes = remove_small_regions(mask, settings.min_area, holes=True)
        mask, changed_islands = remove_small_regions(mask, settings.min_area, holes=False)
        cleaned.append(mask)
        unchanged.append(not (changed_holes or changed_islands))
    masks = torch.from_numpy(np.stack(cleaned)).to(level.masks.device)
    boxes = mask_boxes(masks)
    keep = nms(boxes, torch.tensor(unchanged, dtype=torch.float32, device=boxes.device),
               max(settings.box_nms, settings.crop_nms))
    return replace(level, masks=masks, boxes=boxes).take(keep)


def level_masks(sam: Sam, image: np.ndarray, settings: MaskSettings = MaskSettings()) -> list[Masks]:
    """The masks of ``image`` [H, W, 3] uint8 RGB at each of :data:`LEVELS` (module docstring)."""
    full = image.shape[:2]
    crops = crop_boxes(*full, settings.crop_layers, settings.crop_overlap)
    per_crop = [_crop_masks(sam, image, crop, settings, full) for crop in crops]
    levels = []
    for index in range(len(LEVELS)):
        level = Masks.cat([c[index] for c in per_crop], full, sam.device)
        if len(crops) > 1:
            level = level.take(nms(level.boxes, 1 / level.crop_areas, settings.crop_nms))
        levels.append(_clean(level, settings))
    return levels


def crop_count(settings: MaskSettings) -> int:
    """SAM image embeddings per frame: the whole image and every crop."""
    return sum(4 ** i for i in range(settings.crop_layers + 1))

