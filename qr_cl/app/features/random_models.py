"""Seeded random-weight CLIP and SAM models of any architecture, saved as the files their
publishers ship (OpenCLIP ``.bin``/``.safetensors``, SAM ``.pth``, MobileSAM ``.pt``), so the real
loading code runs without downloaded weights: the tests' small models and the benchmark's
real-size ones. A tiny BPE vocabulary in CLIP's file format goes with the small text towers.

Weights are N(0, 1/fan_in) (LayerNorms 1 and 0, biases 0; BatchNorms 1 and 0 too, with running
means N(0, 0.01) and variances uniform in [0.5, 1.5)). With such weights SAM's predicted IoU and
mask stability are arbitrary, so :func:`random_sam` can lift the IoU head's bias and sharpen the
mask logits (``confident``) for masks to pass LangSplat's thresholds.
"""
from __future__ import annotations

import gzip
import math
from pathlib import Path

import torch
from torch import nn

from .clip_model import Clip, ClipArchitecture
from .sam_encoder import LayerNorm2d
from .sam_model import Sam, SamArchitecture
from .tiny_vit import MOBILE_SAM_ENCODER
from .tokenizer import byte_symbols
from .weights import write_safetensors

#: The real architectures (OpenCLIP's configs; SAM's and MobileSAM's build_sam), for timing.
CLIP_ARCHITECTURES = {
    "ViT-B-16": ClipArchitecture(768, 12, 16, 224, 3072, 512, 512, 12, 77, 49408, 2048, False),
    "ViT-B-32": ClipArchitecture(768, 12, 32, 224, 3072, 512, 512, 12, 77, 49408, 2048, False),
    "ViT-L-14": ClipArchitecture(1024, 24, 14, 224, 4096, 768, 768, 12, 77, 49408, 3072, False),
}
#: Factor on the random SAM's hypernetwork outputs: logits steep enough to be stable at +-1.
SHARPEN = 1000.0
SAM_ARCHITECTURES = {
    "vit_b": SamArchitecture(768, 12, 12, (2, 5, 8, 11)),
    "vit_l": SamArchitecture(1024, 24, 16, (5, 11, 17, 23)),
    "vit_h": SamArchitecture(1280, 32, 16, (7, 15, 23, 31)),
    "mobile_sam": SamArchitecture(tiny_vit=MOBILE_SAM_ENCODER),
}


def randomise(module: nn.Module, seed: int) -> nn.Module:
    """Set every parameter and buffer of ``module`` from a generator seeded with ``seed``
    (module docstring); returns it."""
    gen = torch.Generator().manual_seed(seed)
    norms = {id(m.weight) for m in module.modules() if isinstance(m, (nn.LayerNorm, LayerNorm2d, nn.BatchNorm2d))}
    with torch.no_grad():
        for name, tensor in module.state_dict(keep_vars=True).items():
            if not tensor.is_floating_point():                  # a BatchNorm's num_batches_tracked
                continue
            if id(tensor) in norms:
                tensor.fill_(1.0)
            elif name.endswith("running_mean"):
                tensor.copy_(0.1 * torch.randn(tensor.shape, generator=gen))
            elif name.endswith("running_var"):
                tensor.copy_(0.5 + torch.rand(tensor.shape, generator=gen))
            elif name.endswith("bias") and tensor.ndim == 1:
                tensor.zero_()
            else:
                fan_in = math.prod(tensor.shape[1:]) if tensor.ndim > 1 else max(tensor.numel(), 1)
                tensor.copy_(torch.randn(tensor.shape, generator=gen) / math.sqrt(max(fan_in, 1)))
    return module


def random_clip(arch: ClipArchitecture, seed: int = 0) -> Clip:
    """A CLIP of ``arch`` with seeded random weights."""
    return randomise(Clip(arch), seed).eval()


def random_sam(arch: SamArchitecture, seed: int = 0, confident: bool = True) -> Sam:
    """A SAM of ``arch`` with seeded random weights; ``confident`` lifts the IoU head's output
    bias to 1 and scales the hypernetworks' last layers by :data:`SHARPEN` (sharp, stable mask logits)."""
    sam = randomise(Sam(arch), seed).eval()
    if confident:
        with torch.no_grad():
            sam.mask_decoder.iou_prediction_head.layers[-1].bias.fill_(1.0)
            for mlp in sam.mask_decoder.output_hypernetworks_mlps:
                mlp.layers[-1].weight.mul_(SHARPEN)
    return sam


def save_weights(module: nn.Module, path: str | Path) -> Path:
    """Save ``module``'s state dict as its publishers do: ``.safetensors`` (safetensors), else a
    ``torch.save`` file (``.bin``, ``.pt``, ``.pth``)."""
    path = Path(path)
    state = {k: v.detach().contiguous() for k, v in module.state_dict().items()}
    if path.suffix == ".safetensors":
        write_safetensors(path, state)
    else:
        torch.save(state, path)
    return path


def write_vocabulary(path: str | Path, words: list[str]) -> int:
    """Write a BPE merges file in CLIP's format (gzip text, a version line, one merge per line)
    that spells each of ``words`` (lower case) as one token; returns the vocabulary's size."""
    symbols = byte_symbols()
    merges: list[tuple[str, str]] = []
    for word in words:
        for piece in word.lower().split():
            parts = [symbols[b] for b in piece.encode("utf-8")]
            parts[-1] += "</w>"
            while len(parts) > 1:
                pair = (parts[0], parts[1])
                if pair not in merges:
                    merges.append(pair)
                parts = [parts[0] + parts[1]] + parts[2:]
    text = "#version: test\n" + "\n".join(f"{a} {b}" for a, b in merges) + "\n"
    Path(path).write_bytes(gzip.compress(text.encode("utf-8"), mtime=0))
    return 512 + len(merges) + 2
