"""MobileSAM's image encoder (Zhang et al. 2023), a TinyViT (Wu et al. 2022) distilled from SAM's
ViT-H, in plain torch under the parameter names of the official ``mobile_sam.pt``
(``image_encoder.*``).

Every convolution is bias-free and followed by a BatchNorm (``c``, ``bn``; eval mode: the
checkpoint's running statistics). ``patch_embed`` takes the [3, 1024, 1024] input to [64, 256, 256]
by two 3x3 stride-2 convolutions with a GELU between. Stage 0 (``layers.0``) is MBConv blocks: a
1x1 expansion to 4x the channels, a 3x3 depthwise and a 1x1 projection, GELUs between, the input
added and a last GELU. Stages 1-3 are TinyViT blocks, each: attention in windows (the map
zero-padded to a multiple of the window; the attention's LayerNorm comes after the padding, so
the padded tokens enter as keys), with q, k, v interleaved per head in ``qkv`` and a learned
bias per head for every (|dy|, |dx|) offset between two tokens added to the logits, the input
added; a 3x3 depthwise ``local_conv`` (no shortcut); a pre-norm 2-layer GELU MLP, the input
added. Every stage but the last ends in a patch merging (1x1, 3x3 depthwise, 1x1, GELUs between)
to the next width, stride 2 except into the last stage: 256 -> 128 -> 64 -> 64 px. The neck of
SAM's encoder maps the last [320, 64, 64] map to the 256-channel image embedding. The checkpoint's
ImageNet classifier (``norm_head``, ``head``) is not used.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .errors import FeaturesError
from .sam_encoder import neck

#: Channel expansion of the MBConv blocks and hidden width of the TinyViT blocks' MLP.
MBCONV_EXPAND, MLP_RATIO = 4, 4


@dataclass(frozen=True)
class TinyVitArchitecture:
    """TinyViT's four stages: ``widths`` (channels), ``depths`` (blocks) and, for the attention
    stages, ``heads`` and ``windows`` (tokens per side); 0 for stage 0, which is convolutional."""

    widths: tuple[int, ...]
    depths: tuple[int, ...]
    heads: tuple[int, ...]
    windows: tuple[int, ...]


#: MobileSAM's TinyViT-5M (the official build_sam_vit_t).
MOBILE_SAM_ENCODER = TinyVitArchitecture((64, 128, 160, 320), (2, 2, 6, 2), (0, 4, 5, 10), (0, 7, 14, 7))


def tiny_vit_architecture(state: dict[str, torch.Tensor], path: Path) -> TinyVitArchitecture:
    """The stages of the TinyViT ``image_encoder`` in a state dict: widths from the patch
    embedding and the patch mergings, depths from the blocks, heads and windows from the
    attention-bias tables [heads, window^2]; FeaturesError naming ``path`` for an incomplete one."""
    prefix = "image_encoder.layers."
    stages = {int(k.split(".")[2]) for k in state if k.startswith(prefix)}
    if stages != set(range(4)):
        raise FeaturesError(f"{path}: a TinyViT image encoder with stages {sorted(stages)}, not 0-3 (--sam-weights)")
    try:
        widths = (state["image_encoder.patch_embed.seq.2.c.weight"].shape[0],
                  *(state[f"{prefix}{i}.downsample.conv1.c.weight"].shape[0] for i in range(3)))
        biases = [state[f"{prefix}{i}.blocks.0.attn.attention_biases"].shape for i in range(1, 4)]
    except KeyError as exc:
        raise FeaturesError(f"{path}: a TinyViT image encoder without {exc.args[0]} (--sam-weights)") from None
    depths = tuple(len({k.split(".")[4] for k in state if k.startswith(f"{prefix}{i}.blocks.")}) for i in range(4))
    windows = tuple(math.isqrt(shape[1]) for shape in biases)
    if any(w * w != shape[1] for w, shape in zip(windows, biases)):
        raise FeaturesError(f"{path}: TinyViT attention biases {[list(s) for s in biases]} are no square windows "
                            "(--sam-weights)")
    return TinyVitArchitecture(widths, depths, (0, *(shape[0] for shape in biases)), (0, *windows))


class ConvBN(nn.Module):
    """``c``: a bias-free convolution ('same' padding), ``bn``: its BatchNorm, applied with its
    running statistics folded into the convolution (one pass over the map; inference only)."""

    def __init__(self, cin: int, cout: int, kernel: int = 1, stride: int = 1, groups: int = 1):
        super().__init__()
        self.c = nn.Conv2d(cin, cout, kernel, stride, kernel // 2, groups=groups, bias=False)
        self.bn = nn.BatchNorm2d(cout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        c, bn = self.c, self.bn
        scale = bn.weight * torch.rsqrt(bn.running_var + bn.eps)
        return F.conv2d(x, c.weight * scale[:, None, None, None], bn.bias - bn.running_mean * scale, c.stride,
                        c.padding, groups=c.groups)


class PatchEmbed(nn.Module):
    """``seq``: [B, 3, H, W] -> [B, dim, H/4, W/4] by two 3x3 stride-2 convolutions, GELU between."""

    def __init__(self, dim: int):
        super().__init__()
        self.seq = nn.Sequential(ConvBN(3, dim // 2, 3, 2), nn.GELU(), ConvBN(dim // 2, dim, 3, 2))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.seq(x)


class MBConv(nn.Module):
    """GELU(x + conv3(GELU(conv2(GELU(conv1(x)))))): 1x1 expansion, 3x3 depthwise, 1x1 projection."""

    def __init__(self, dim: int):
        super().__init__()
        hidden = MBCONV_EXPAND * dim
        self.conv1 = ConvBN(dim, hidden)
        self.conv2 = ConvBN(hidden, hidden, 3, groups=hidden)
        self.conv3 = ConvBN(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.gelu(x + self.conv3(F.gelu(self.conv2(F.gelu(self.conv1(x))))))


class PatchMerging(nn.Module):
    """[B, dim, H, W] -> [B, out, H/stride, W/stride]: 1x1, 3x3 depthwise (``stride``), 1x1, GELUs between."""

    def __init__(self, dim: int, out: int, stride: int):
        super().__init__()
        self.conv1 = ConvBN(dim, out)
        self.conv2 = ConvBN(out, out, 3, stride, groups=out)
        self.conv3 = ConvBN(out, out)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv3(F.gelu(self.conv2(F.gelu(self.conv1(x)))))


def offset_index(window: int) -> torch.Tensor:
    """[window^2, window^2] column of each pair of tokens (row-major in the window) in the bias
    table: |dy| * window + |dx|. (The official code numbers offsets in the order it meets them,
    from token (0, 0) first: the same numbers.)"""
    idx = torch.arange(window * window)
    y, x = idx // window, idx % window
    return (y[:, None] - y[None]).abs() * window + (x[:, None] - x[None]).abs()


class Attention(nn.Module):
    """Pre-norm multi-head attention over [B, N, C] tokens of a window x window window: ``qkv``
    gives each head's q, k, v side by side; ``attention_biases`` [heads, window^2] per offset."""

    def __init__(self, dim: int, heads: int, window: int):
        super().__init__()
        self.heads = heads
        self.norm = nn.LayerNorm(dim)
        self.qkv, self.proj = nn.Linear(dim, 3 * dim), nn.Linear(dim, dim)
        self.attention_biases = nn.Parameter(torch.zeros(heads, window * window))
        self.register_buffer("attention_bias_idxs", offset_index(window), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        qkv = self.qkv(self.norm(x)).view(b, n, self.heads, 3, c // self.heads)
        q, k, v = qkv.permute(3, 0, 2, 1, 4)                                       # [B, heads, N, d]
        bias = self.attention_biases[:, self.attention_bias_idxs]                  # [heads, N, N]
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=bias)
        return self.proj(y.transpose(1, 2).reshape(b, n, c))


class Mlp(nn.Module):
    """``norm`` -> ``fc1`` -> GELU -> ``fc2``."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.fc1, self.fc2 = nn.Linear(dim, hidden), nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(self.norm(x))))


class TinyViTBlock(nn.Module):
    """[B, C, H, W] -> the same: x + windowed attention, ``local_conv``, x + MLP (module docstring)."""

    def __init__(self, dim: int, heads: int, window: int):
        super().__init__()
        self.window = window
        self.attn = Attention(dim, heads, window)
        self.local_conv = ConvBN(dim, dim, 3, groups=dim)
        self.mlp = Mlp(dim, MLP_RATIO * dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, c, h, w = x.shape
        n = self.window
        x = x.permute(0, 2, 3, 1)                                                  # [B, H, W, C]
        ph, pw = -h % n, -w % n
        gh, gw = (h + ph) // n, (w + pw) // n
        y = F.pad(x, (0, 0, 0, pw, 0, ph)).reshape(b, gh, n, gw, n, c).transpose(2, 3).reshape(-1, n * n, c)
        y = self.attn(y).view(b, gh, gw, n, n, c).transpose(2, 3).reshape(b, gh * n, gw * n, c)   # windows back
        x = self.local_conv((x + y[:, :h, :w]).permute(0, 3, 1, 2)).permute(0, 2, 3, 1)
        return (x + self.mlp(x)).permute(0, 3, 1, 2)


class Stage(nn.Module):
    """``blocks`` (MBConv in stage 0, else TinyViT blocks), then ``downsample`` (a
    :class:`PatchMerging`) unless it is the last stage."""

    def __init__(self, arch: TinyVitArchitecture, i: int):
        super().__init__()
        dim, last = arch.widths[i], len(arch.widths) - 1
        self.blocks = nn.ModuleList(MBConv(dim) if i == 0 else TinyViTBlock(dim, arch.heads[i], arch.windows[i])
                                    for _ in range(arch.depths[i]))
        self.downsample = PatchMerging(dim, arch.widths[i + 1], 1 if i + 1 == last else 2) if i < last else None

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for block in self.blocks:
            x = block(x)
        return x if self.downsample is None else self.downsample(x)


class TinyViT(nn.Module):
    """MobileSAM's image encoder: [B, 3, 1024, 1024] normalised pixels -> [B, 256, 64, 64]."""

    def __init__(self, arch: TinyVitArchitecture = MOBILE_SAM_ENCODER):
        super().__init__()
        self.patch_embed = PatchEmbed(arch.widths[0])
        self.layers = nn.ModuleList(Stage(arch, i) for i in range(len(arch.widths)))
        self.neck = neck(arch.widths[-1])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.patch_embed(x)
        for layer in self.layers:
            x = layer(x)
        return self.neck(x)
