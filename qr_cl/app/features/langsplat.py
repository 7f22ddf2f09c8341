"""LangSplat's steps after SAM: its overlap filter per level, the id map per level, and each
mask's crop for CLIP.

- Filter (LangSplat's ``masks_update``/``mask_nms`` with iou 0.8, score 0.7, inner 0.5): masks
  are ranked by stability x predicted IoU; a mask is dropped when a better-ranked one overlaps it
  by IoU > 0.8, when its score is <= 0.7, or when it and another mask nest (one covers >= 85% of
  the other, which covers < 50% of it) with 1 - (both cover ratios' product) > 0.5 on the side
  LangSplat looks at. Where the score or a nesting rule would drop every mask, its best three
  (at most) are kept from that rule. Survivors keep the generator's order.
- Id map: -1, then each mask's pixels set to its index in order (later masks win overlaps).
- Crop: the image with the pixels outside the mask black, cut to the mask's box (LangSplat's
  ``image[y:y+h, x:x+w]`` with w = x1 - x0, which leaves out the box's last row and column; at
  least one pixel here), centred in a black square and resized to the CLIP input (bilinear,
  rounded to 8 bits as ``cv2.resize`` of uint8 images gives).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F

from .masks import Masks

#: LangSplat's filter thresholds.
IOU_THRESHOLD, SCORE_THRESHOLD, INNER_THRESHOLD = 0.8, 0.7, 0.5
#: Cover ratios of LangSplat's nesting rule.
COVERED, NOT_COVERING = 0.85, 0.5


def overlap_filter(level: Masks, iou_thr: float = IOU_THRESHOLD, score_thr: float = SCORE_THRESHOLD,
                   inner_thr: float = INNER_THRESHOLD) -> Masks:
    """The masks of ``level`` that LangSplat's filter keeps (module docstring), in their order."""
    n = len(level)
    if n == 0:
        return level
    scores = level.stability * level.iou
    order = torch.sort(scores, descending=True, stable=True).indices
    scores = scores[order]
    flat = level.masks[order].flatten(1).float()
    area = flat.sum(1)
    inter = flat @ flat.T
    iou = (inter / (area[:, None] + area[None, :] - inter)).triu(1)
    cover_row, cover_col = inter / area[:, None], inter / area[None, :]
    nested = (cover_row < NOT_COVERING) & (cover_col >= COVERED)
    inner = torch.where(nested, 1 - cover_row * cover_col, torch.zeros_like(inter))
    keep = iou.amax(0) <= iou_thr
    best = torch.zeros(n, dtype=torch.bool, device=keep.device)
    best[torch.topk(scores, min(3, n)).indices] = True
    for rule in (scores > score_thr, inner.triu(1).amax(0) <= 1 - inner_thr, inner.tril(1).amax(0) <= 1 - inner_thr):
        keep &= rule if rule.any() else best
    kept = torch.sort(order[keep]).values
    return level.take(kept)


def id_map(level: Masks) -> torch.Tensor:
    """[H, W] int32: -1 where no mask, else the index of the last mask covering the pixel."""
    n, h, w = level.masks.shape
    ids = torch.arange(n, dtype=torch.int32, device=level.masks.device)[:, None, None]
    top = torch.where(level.masks, ids, -1).amax(0) if n else torch.full((h, w), -1, dtype=torch.int32)
    return top.to(torch.int32)


def mask_crops(image: torch.Tensor, level: Masks, size: int) -> torch.Tensor:
    """[n, 3, size, size] float crops in [0, 1] of ``image`` [H, W, 3] uint8 (on the masks'
    device) for each mask of ``level`` (module docstring)."""
    crops = []
    for mask, box in zip(level.masks, level.boxes.to(torch.int64).tolist()):
        x0, y0, x1, y1 = box
        w, h = max(x1 - x0, 1), max(y1 - y0, 1)
        cut = torch.where(mask[y0:y0 + h, x0:x0 + w, None], image[y0:y0 + h, x0:x0 + w], 0)
        side = max(w, h)
        square = torch.zeros(side, side, 3, dtype=torch.uint8, device=image.device)
        top, left = (side - h) // 2, (side - w) // 2
        square[top:top + h, left:left + w] = cut
        crops.append(square.permute(2, 0, 1).float())
    resized = [F.interpolate(c[None], size=(size, size), mode="bilinear", align_corners=False) for c in crops]
    if not resized:
        return torch.zeros(0, 3, size, size, device=image.device)
    return torch.cat(resized).round().clamp(0, 255) / 255
