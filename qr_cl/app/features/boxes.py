"""Boxes of masks and greedy non-maximum suppression, as SAM's automatic mask generator uses
them. Boxes are [n, 4] (x0, y0, x1, y1) with inclusive pixel bounds (x1 the last column)."""
from __future__ import annotations

import torch


def mask_boxes(masks: torch.Tensor) -> torch.Tensor:
    """[n, 4] float boxes of ``masks`` [n, H, W] bool ((0, 0, 0, 0) for an empty mask)."""
    n, h, w = masks.shape
    if n == 0:
        return torch.zeros(0, 4, device=masks.device)
    as_bytes = masks.view(torch.uint8)                   # a max over bytes: bool any() was 20x slower
    rows, cols = as_bytes.amax(2) > 0, as_bytes.amax(1) > 0
    ys = torch.arange(h, device=masks.device)
    xs = torch.arange(w, device=masks.device)
    y1 = (rows * ys).amax(1)
    x1 = (cols * xs).amax(1)
    y0 = torch.where(rows, ys, h).amin(1)
    x0 = torch.where(cols, xs, w).amin(1)
    empty = ~rows.any(1)
    boxes = torch.stack([x0, y0, x1, y1], 1).float()
    boxes[empty] = 0
    return boxes


def box_areas(boxes: torch.Tensor) -> torch.Tensor:
    """[n] (x1 - x0) * (y1 - y0) of ``boxes`` [n, 4]."""
    return (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """[n, m] intersection over union of boxes ``a`` [n, 4] and ``b`` [m, 4] (areas as
    :func:`box_areas`; 0/0 gives NaN, which suppresses nothing)."""
    lo = torch.maximum(a[:, None, :2], b[None, :, :2])
    hi = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (hi - lo).clamp(min=0).prod(-1)
    return inter / (box_areas(a)[:, None] + box_areas(b)[None, :] - inter)


def nms(boxes: torch.Tensor, scores: torch.Tensor, threshold: float) -> torch.Tensor:
    """Indices of the boxes greedy non-maximum suppression keeps, by decreasing score (ties in
    index order): each box, in that order, removes the later ones overlapping it by IoU >
    ``threshold``."""
    order = torch.sort(scores, descending=True, stable=True).indices
    iou = box_iou(boxes[order], boxes[order]).cpu()
    alive = torch.ones(len(order), dtype=torch.bool)
    for i in range(len(order)):
        if alive[i]:
            alive[i + 1:] &= ~(iou[i, i + 1:] > threshold)
    return order[alive.to(order.device)]


def near_crop_edge(boxes: torch.Tensor, crop: tuple[int, int, int, int], image: tuple[int, int, int, int],
                   tolerance: float = 20.0) -> torch.Tensor:
    """[n] bool: boxes (image coordinates) within ``tolerance`` px of an edge of the ``crop``
    box (x0, y0, x1, y1) that is not also an edge of the ``image`` box."""
    crop_t = torch.tensor(crop, dtype=torch.float32, device=boxes.device)
    image_t = torch.tensor(image, dtype=torch.float32, device=boxes.device)
    at_crop = torch.isclose(boxes, crop_t[None], atol=tolerance, rtol=0)
    at_image = torch.isclose(boxes, image_t[None], atol=tolerance, rtol=0)
    return (at_crop & ~at_image).any(1)
