"""The path ``qr-cl features`` took before its decoder was rearranged, kept as the reference the
fast path is compared with: SAM's :class:`MaskDecoder` as published (every prompt through the
whole decoder, four masks), dense upsampling of every mask to the crop's size, the filters on the
upsampled logits, and CLIP on every mask of every level."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from qr_cl.app.features.boxes import mask_boxes, near_crop_edge, nms
from qr_cl.app.features.frames import FrameFeatures, encode_crops
from qr_cl.app.features.langsplat import id_map, mask_crops, overlap_filter
from qr_cl.app.features.mask_upsampling import stability_scores
from qr_cl.app.features.masks import LEVELS, MaskSettings, Masks, _clean, crop_boxes, point_grid
from qr_cl.app.features.sam_model import upsampling_matrix


def reference_predict(view, points: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """(logits [B, 3, H, W], IoU [B, 3]) of the multimask outputs by the published decoder."""
    sam, (h, w), (rh, rw) = view.sam, view.size, view.resized
    xy = torch.as_tensor(points, dtype=torch.float32) * torch.tensor([rw / w, rh / h])
    with torch.no_grad():
        sparse = sam.prompt_encoder.embed_points(xy[:, None], torch.ones(len(xy), 1))
        dense = sam.prompt_encoder.no_mask_embed.weight.view(1, -1, 1, 1)
        low, iou = sam.mask_decoder(view.embedding, view.positions, sparse, dense)
        ay, ax = upsampling_matrix(h, rh, low.shape[-2]), upsampling_matrix(w, rw, low.shape[-1])
        return ay @ low[:, 1:] @ ax.T, iou[:, 1:]


def _reference_crop(sam, image, crop, settings: MaskSettings, full) -> list[Masks]:
    x0, y0, x1, y1 = crop
    view = sam.embed(np.ascontiguousarray(image[y0:y1, x0:x1]))
    ch, cw = y1 - y0, x1 - x0
    points = point_grid(settings.points_per_side) * np.array([cw, ch])
    offset = torch.tensor([x0, y0, x0, y0], dtype=torch.float32)
    kept = [[] for _ in LEVELS]
    for start in range(0, len(points), settings.points_per_batch):
        logits, iou = reference_predict(view, points[start:start + settings.points_per_batch])
        logits, iou = logits.flatten(0, 1), iou.flatten()
        output = torch.arange(len(iou)) % 3
        keep = iou > settings.pred_iou
        logits, iou, output = logits[keep], iou[keep], output[keep]
        stab = stability_scores(logits, settings.stability_offset)
        keep = stab >= settings.stability
        masks, iou, stab, output = logits[keep] > 0, iou[keep], stab[keep], output[keep]
        boxes = mask_boxes(masks) + offset
        keep = ~near_crop_edge(boxes, crop, (0, 0, full[1], full[0]))
        found = Masks(masks[keep], boxes[keep], iou[keep], stab[keep], torch.full((int(keep.sum()),), float(cw * ch)))
        for level, sel in enumerate([None, 0, 1, 2]):
            kept[level].append(found if sel is None else found.take(output[keep] == sel))
    result = []
    for parts in kept:
        level = Masks.cat(parts, (ch, cw), "cpu")
        level = level.take(nms(level.boxes, level.iou, settings.box_nms))
        placed = torch.zeros(len(level), *full, dtype=torch.bool)
        placed[:, y0:y1, x0:x1] = level.masks
        result.append(replace(level, masks=placed))
    return result


def reference_frame(sam, clip, image: np.ndarray, settings: MaskSettings, batch: int = 32) -> FrameFeatures:
    """The frame's features (:func:`~qr_cl.app.features.frames.frame_features`) by the old path."""
    full = image.shape[:2]
    crops = crop_boxes(*full, settings.crop_layers, settings.crop_overlap)
    per_crop = [_reference_crop(sam, image, crop, settings, full) for crop in crops]
    pixels = torch.from_numpy(image.copy())
    maps, rows, counts, offset = [], [], [], 0
    for index in range(len(LEVELS)):
        level = Masks.cat([c[index] for c in per_crop], full, "cpu")
        if len(crops) > 1:
            level = level.take(nms(level.boxes, 1 / level.crop_areas, settings.crop_nms))
        level = overlap_filter(_clean(level, settings))
        ids = id_map(level)
        maps.append(torch.where(ids >= 0, ids + offset, -1))
        rows.append(encode_crops(clip, mask_crops(pixels, level, clip.arch.image_size), batch))
        counts.append(len(level))
        offset += len(level)
    return FrameFeatures(torch.stack(maps).numpy().astype(np.float32), torch.cat(rows).numpy().astype(np.float32),
                         counts)
