"""SAM (ViT-B/L/H) or MobileSAM (a TinyViT image encoder, SAM's prompt encoder and mask decoder)
from its official checkpoint, the variant read from the weight shapes, and point-prompted mask
prediction on one image.

:class:`Sam` holds ``image_encoder``, ``prompt_encoder`` and ``mask_decoder`` as the checkpoints
name them. :class:`SamImage` is one image's embedding: the image is resized so its longer side is
1024 px (bilinear, PIL), normalised by SAM's pixel mean and deviation, zero-padded to 1024x1024
and encoded once. Batches of single-point prompts are then decoded into the three multimask
outputs (:meth:`SamImage.decode`, :meth:`SamImage.low_masks`: SAM's decoder rearranged for many
prompts, :mod:`.point_decoder`) and upsampled to the image's own size (:meth:`SamImage.upsample`:
the 256x256 logits upsampled to 1024, cropped to the resized image and upsampled to the original
size, both bilinear, as a few taps per row and column, :mod:`.mask_upsampling`);
:meth:`SamImage.predict` does all three.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image
from torch import nn

from .errors import FeaturesError
from .mask_upsampling import Taps, upsample
from .point_decoder import UPSCALE, PointDecoder, PromptTokens
from .sam_decoder import MaskDecoder, PromptEncoder
from .sam_encoder import SAM_IMAGE_SIZE, SAM_PATCH, WINDOW, ImageEncoder
from .tiny_vit import MOBILE_SAM_ENCODER, TinyViT, TinyVitArchitecture, tiny_vit_architecture
from .weights import load_state_dict, missing_keys

#: SAM's pixel normalisation (0-255 RGB).
PIXEL_MEAN = (123.675, 116.28, 103.53)
PIXEL_STD = (58.395, 57.12, 57.375)
#: Variants by image-encoder width: name and attention heads.
VARIANTS = {768: ("vit_b", 12), 1024: ("vit_l", 16), 1280: ("vit_h", 16)}
#: The first weight of each image encoder: SAM's ViT, MobileSAM's TinyViT.
VIT_KEY, TINY_VIT_KEY = "image_encoder.patch_embed.proj.weight", "image_encoder.patch_embed.seq.0.c.weight"


@dataclass(frozen=True)
class SamArchitecture:
    """SAM's image encoder shape. A ViT (SAM): ``width``, ``depth``, ``heads`` and the
    ``global_blocks`` (those attending over the whole map, the others over 14x14 windows). A
    TinyViT (MobileSAM): its stages ``tiny_vit``, the ViT fields left 0."""

    width: int = 0
    depth: int = 0
    heads: int = 0
    global_blocks: tuple[int, ...] = ()
    tiny_vit: TinyVitArchitecture | None = None

    @property
    def name(self) -> str:
        """``vit_b``, ``vit_l``, ``vit_h`` (or ``vit_w<width>`` for another width); ``mobile_sam``
        (or ``tiny_vit_w<widths>`` for other TinyViT stages)."""
        if self.tiny_vit:
            widths = "-".join(map(str, self.tiny_vit.widths))
            return "mobile_sam" if self.tiny_vit == MOBILE_SAM_ENCODER else f"tiny_vit_w{widths}"
        return VARIANTS.get(self.width, (f"vit_w{self.width}", 0))[0]


def sam_architecture(state: dict[str, torch.Tensor], path: Path) -> SamArchitecture:
    """The encoder shape of a SAM state dict: a ViT's width from the patch embedding, depth from
    the blocks, global blocks from their relative-position tables (2*64-1 rows against 2*14-1),
    heads from the table's width (head dim); a TinyViT's stages (:func:`tiny_vit_architecture`).
    FeaturesError naming ``path`` when it is neither SAM nor MobileSAM."""
    if TINY_VIT_KEY in state:
        return SamArchitecture(tiny_vit=tiny_vit_architecture(state, path))
    if VIT_KEY not in state:
        kind = "a CLIP checkpoint" if "visual.conv1.weight" in state else "not a SAM checkpoint"
        raise FeaturesError(f"{path}: {kind}: lacks {VIT_KEY} (SAM) or {TINY_VIT_KEY} (MobileSAM) (--sam-weights)")
    width = state[VIT_KEY].shape[0]
    depth = len({k.split(".")[2] for k in state if k.startswith("image_encoder.blocks.")})
    rows = [state[f"image_encoder.blocks.{i}.attn.rel_pos_h"].shape for i in range(depth)
            if f"image_encoder.blocks.{i}.attn.rel_pos_h" in state]
    if len(rows) != depth:
        raise FeaturesError(f"{path}: image encoder blocks without relative positions (--sam-weights)")
    global_blocks = tuple(i for i, shape in enumerate(rows) if shape[0] != 2 * WINDOW - 1)
    return SamArchitecture(width, depth, width // rows[0][1], global_blocks)


class Sam(nn.Module):
    """SAM: ``image_encoder``, ``prompt_encoder``, ``mask_decoder`` (mask threshold 0 on logits)."""

    def __init__(self, arch: SamArchitecture):
        super().__init__()
        self.arch = arch
        self.image_encoder = (TinyViT(arch.tiny_vit) if arch.tiny_vit else
                              ImageEncoder(arch.width, arch.depth, arch.heads, arch.global_blocks))
        self.prompt_encoder = PromptEncoder()
        self.mask_decoder = MaskDecoder()
        self.register_buffer("pixel_mean", torch.tensor(PIXEL_MEAN).view(-1, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(PIXEL_STD).view(-1, 1, 1), persistent=False)

    @property
    def device(self) -> torch.device:
        return self.pixel_mean.device

    def embed(self, image: np.ndarray) -> "SamImage":
        """The embedding of ``image`` [H, W, 3] uint8 RGB (module docstring)."""
        h, w = image.shape[:2]
        scale = SAM_IMAGE_SIZE / max(h, w)
        rh, rw = int(h * scale + 0.5), int(w * scale + 0.5)
        resized = np.asarray(Image.fromarray(image).resize((rw, rh), Image.BILINEAR))
        x = torch.from_numpy(resized.copy()).to(self.device).permute(2, 0, 1).float()
        x = F.pad((x - self.pixel_mean) / self.pixel_std, (0, SAM_IMAGE_SIZE - rw, 0, SAM_IMAGE_SIZE - rh))
        with torch.no_grad():
            embedding = self.image_encoder(x[None])
            pe = self.prompt_encoder.pe_layer.grid(SAM_IMAGE_SIZE // SAM_PATCH)[None]
        return SamImage(self, embedding, pe, (h, w), (rh, rw))


def upsampling_matrix(out: int, crop: int, low: int) -> torch.Tensor:
    """[out, low] linear map of one axis: ``low`` logits upsampled bilinearly (half-pixel
    centres) to 1024, the first ``crop`` kept, upsampled to ``out``."""
    eye = torch.eye(low, dtype=torch.float64)[None]
    up = F.interpolate(eye, size=SAM_IMAGE_SIZE, mode="linear", align_corners=False)[..., :crop]
    return F.interpolate(up, size=out, mode="linear", align_corners=False)[0].T.float()


@dataclass
class SamImage:
    """One image's SAM embedding [1, 256, 64, 64] and dense positions; ``size`` (H, W) of the
    image, ``resized`` (H, W) of it in the 1024 input. Prompts are decoded by a
    :class:`~.point_decoder.PointDecoder` of the embedding, and the masks upsampled by the taps
    ``rows`` and ``cols`` of SAM's resizes (:mod:`.mask_upsampling`)."""

    sam: Sam
    embedding: torch.Tensor
    positions: torch.Tensor
    size: tuple[int, int]
    resized: tuple[int, int]

    def __post_init__(self):
        sam, (h, w), (rh, rw) = self.sam, self.size, self.resized
        dense = sam.prompt_encoder.no_mask_embed.weight.view(1, -1, 1, 1)
        self.decoder = PointDecoder(sam.mask_decoder, self.embedding, self.positions, dense)
        low = SAM_IMAGE_SIZE // SAM_PATCH * UPSCALE
        self.rows = Taps.of(upsampling_matrix(h, rh, low)).to(sam.device)
        self.cols = Taps.of(upsampling_matrix(w, rw, low)).to(sam.device)

    def decode(self, points: np.ndarray) -> tuple[PromptTokens, torch.Tensor]:
        """(the decoder's tokens, predicted IoU [B, 3] of the three multimask outputs) for
        ``points`` [B, 2] (x, y px in the image), one foreground point per prompt."""
        sam, (h, w), (rh, rw) = self.sam, self.size, self.resized
        xy = torch.as_tensor(points, dtype=torch.float32, device=sam.device) * torch.tensor(
            [rw / w, rh / h], device=sam.device)
        with torch.no_grad():
            sparse = sam.prompt_encoder.embed_points(xy[:, None], torch.ones(len(xy), 1, device=sam.device))
        tokens = self.decoder.transform(sparse)
        return tokens, self.decoder.iou(tokens)

    def low_masks(self, tokens: PromptTokens) -> torch.Tensor:
        """[B, 3, h, w] low-resolution logits of the three multimask outputs over the part of
        SAM's 256x256 grid that the upsampling reads."""
        return self.decoder.masks(tokens, -(-self.rows.reads // UPSCALE), -(-self.cols.reads // UPSCALE))

    def upsample(self, low: torch.Tensor) -> torch.Tensor:
        """[..., H, W] logits at the image's size of ``low`` [..., h, w] (:meth:`low_masks`)."""
        return upsample(low, self.rows, self.cols)

    def predict(self, points: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """(logits [B, 3, H, W], predicted IoU [B, 3]) of the three multimask outputs for ``points``
        [B, 2] (x, y px in the image), one foreground point per prompt."""
        tokens, iou = self.decode(points)
        return self.upsample(self.low_masks(tokens)), iou


def load_sam(path: str | os.PathLike) -> Sam:
    """SAM from an official ``sam_vit_{b,l,h}`` checkpoint or MobileSAM from ``mobile_sam.pt``
    (variant from the shapes; CPU, float32, eval mode: BatchNorms use their running statistics;
    weights the model lacks, like MobileSAM's classifier head, are ignored); FeaturesError naming
    the file for a missing, unreadable or foreign one."""
    path = Path(path)
    state, _ = load_state_dict(path, "--sam-weights")
    arch = sam_architecture(state, path)
    net = Sam(arch)
    state = {k: v for k, v in state.items() if k in net.state_dict()}
    absent = missing_keys(state, net)
    if absent:
        raise FeaturesError(f"{path}: a SAM {arch.name} lacks {len(absent)} weights, e.g. {absent[0]} (--sam-weights)")
    try:
        net.load_state_dict({k: v.float() for k, v in state.items()})
    except RuntimeError as exc:
        raise FeaturesError(f"{path}: weights do not fit a SAM {arch.name}: {str(exc).splitlines()[-1].strip()}") from None
    return net.eval()
