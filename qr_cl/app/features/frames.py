"""One frame's LangSplat features: SAM's masks at the four levels, LangSplat's filter, one CLIP
image embedding per mask crop, and the stacked files' arrays.

``_s.npy`` [4, H, W] float32 holds per level the mask ids (row indices into ``_f.npy``) or -1,
level j's ids offset by the mask counts of the levels before it; ``_f.npy`` [M, E] float32 holds
the unit CLIP embeddings of all levels' masks, level by level (LangSplat's dtypes and layout).
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np
import torch

from .clip_model import IMAGE_MEAN, IMAGE_STD, Clip
from .langsplat import id_map, mask_crops, overlap_filter
from .masks import MaskSettings, level_masks
from .sam_model import Sam


@dataclass
class FrameFeatures:
    """``ids`` [4, H, W] float32 (-1 = no mask), ``features`` [M, E] float32 unit rows,
    ``counts`` masks per level."""

    ids: np.ndarray
    features: np.ndarray
    counts: list[int]


def encode_crops(clip: Clip, crops: torch.Tensor, batch: int) -> torch.Tensor:
    """[n, E] unit CLIP image embeddings of ``crops`` [n, 3, S, S] in [0, 1], ``batch`` at a time."""
    mean = torch.tensor(IMAGE_MEAN, device=crops.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGE_STD, device=crops.device).view(1, 3, 1, 1)
    out = []
    with torch.no_grad():
        for start in range(0, len(crops), batch):
            out.append(clip.encode_image((crops[start:start + batch] - mean) / std))
    if not out:
        return torch.zeros(0, clip.arch.embed_dim, device=crops.device)
    rows = torch.cat(out).float()
    return rows / rows.norm(dim=1, keepdim=True).clamp_min(1e-12)


def mask_keys(masks: torch.Tensor) -> list[bytes]:
    """A digest of each mask of ``masks`` [n, H, W] bool: equal masks, equal keys."""
    bits = np.packbits(masks.flatten(1).cpu().numpy(), axis=1)
    return [hashlib.blake2b(row.tobytes(), digest_size=16).digest() for row in bits]


def frame_features(sam: Sam, clip: Clip, image: np.ndarray, settings: MaskSettings = MaskSettings(),
                   batch: int = 32) -> FrameFeatures:
    """The features of ``image`` [H, W, 3] uint8 RGB (module docstring); ``batch`` crops go through
    CLIP at a time. A mask that recurs at several levels (the default level holds the others'
    masks) is cropped and encoded once: its crop depends on the mask alone."""
    pixels = torch.from_numpy(image.copy()).to(sam.device)
    maps, rows, counts = [], [], []
    encoded: dict[bytes, torch.Tensor] = {}
    offset = 0
    for level in level_masks(sam, image, settings):
        level = overlap_filter(level)
        ids = id_map(level)
        maps.append(torch.where(ids >= 0, ids + offset, -1))
        keys = mask_keys(level.masks)
        new = sorted({k: i for i, k in enumerate(keys) if k not in encoded}.values())
        crops = mask_crops(pixels, level.take(torch.tensor(new, dtype=torch.long)), clip.arch.image_size)
        encoded.update(zip((keys[i] for i in new), encode_crops(clip, crops.to(sam.device), batch)))
        rows.append(torch.stack([encoded[k] for k in keys]) if keys else
                    torch.zeros(0, clip.arch.embed_dim, device=sam.device))
        counts.append(len(level))
        offset += len(level)
    ids = torch.stack(maps).cpu().numpy().astype(np.float32)
    return FrameFeatures(ids, torch.cat(rows).cpu().numpy().astype(np.float32), counts)
