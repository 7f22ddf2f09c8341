"""SAM's image encoder (Kirillov et al. 2023) in plain torch, under the parameter names of the
official ``sam_vit_{b,l,h}`` checkpoints (``image_encoder.*``).

A 16x16 patch embedding of the 1024x1024 input ([64, 64, C] tokens, channels last) plus learned
absolute positions; pre-norm blocks of multi-head attention with decomposed relative positions
(Li et al., MViTv2: a learned table per axis added to the attention logits), in 14x14 windows
(the map zero-padded to a multiple of 14) except in the global blocks; a 2-layer GELU MLP; then a
neck of 1x1 and 3x3 convolutions, each followed by a channel LayerNorm, to 256 channels.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

#: Side of the square input SAM's encoder takes, px, and its patch size.
SAM_IMAGE_SIZE, SAM_PATCH = 1024, 16
#: Windows of the non-global blocks, in tokens per side.
WINDOW = 14
#: Channels of the image embedding (the neck's output).
EMBED_CHANNELS = 256


class LayerNorm2d(nn.Module):
    """LayerNorm over the channels of [B, C, H, W] (eps 1e-6)."""

    def __init__(self, channels: int, eps: float = 1e-6):
        super().__init__()
        self.weight, self.bias = nn.Parameter(torch.ones(channels)), nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        mean = x.mean(1, keepdim=True)
        var = (x - mean).pow(2).mean(1, keepdim=True)
        return self.weight[:, None, None] * ((x - mean) / torch.sqrt(var + self.eps)) + self.bias[:, None, None]


def relative_table(size: int, table: torch.Tensor) -> torch.Tensor:
    """[size, size, D] rows of a relative-position ``table`` [2*size-1, D] (linearly resized
    first when it was learned for another size) for query i and key j: row (i - j) + size - 1."""
    if table.shape[0] != 2 * size - 1:
        table = F.interpolate(table.T[None], size=2 * size - 1, mode="linear")[0].T
    idx = torch.arange(size, device=table.device)
    return table[idx[:, None] - idx[None, :] + size - 1]


class WindowAttention(nn.Module):
    """Multi-head attention over a [B, H, W, C] token map with decomposed relative positions
    (``rel_pos_h``, ``rel_pos_w`` [2*size-1, head dim])."""

    def __init__(self, dim: int, heads: int, size: int):
        super().__init__()
        self.heads = heads
        self.qkv, self.proj = nn.Linear(dim, 3 * dim), nn.Linear(dim, dim)
        self.rel_pos_h = nn.Parameter(torch.zeros(2 * size - 1, dim // heads))
        self.rel_pos_w = nn.Parameter(torch.zeros(2 * size - 1, dim // heads))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, h, w, c = x.shape
        q, k, v = self.qkv(x).view(b, h * w, 3, self.heads, -1).permute(2, 0, 3, 1, 4)   # [B, heads, HW, d]
        rh, rw = relative_table(h, self.rel_pos_h), relative_table(w, self.rel_pos_w)
        grid_q = q.reshape(b, self.heads, h, w, -1)
        bias_h = torch.einsum("bnhwd,hkd->bnhwk", grid_q, rh)
        bias_w = torch.einsum("bnhwd,wkd->bnhwk", grid_q, rw)
        bias = (bias_h[..., :, None] + bias_w[..., None, :]).reshape(b, self.heads, h * w, h * w)
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=bias)
        return self.proj(y.transpose(1, 2).reshape(b, h, w, c))


class MlpBlock(nn.Module):
    """``lin1`` -> GELU -> ``lin2``."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.lin1, self.lin2 = nn.Linear(dim, hidden), nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.lin2(F.gelu(self.lin1(x)))


class EncoderBlock(nn.Module):
    """x + attn(norm1(x)) (in windows when ``window`` > 0), then + mlp(norm2(x))."""

    def __init__(self, dim: int, heads: int, window: int, grid: int):
        super().__init__()
        self.window = window
        self.norm1, self.norm2 = nn.LayerNorm(dim, eps=1e-6), nn.LayerNorm(dim, eps=1e-6)
        self.attn = WindowAttention(dim, heads, window or grid)
        self.mlp = MlpBlock(dim, 4 * dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = self.norm1(x)
        if self.window:
            b, h, w, c = y.shape
            n = self.window
            ph, pw = -h % n, -w % n
            y = F.pad(y, (0, 0, 0, pw, 0, ph))
            gh, gw = (h + ph) // n, (w + pw) // n
            y = y.view(b, gh, n, gw, n, c).permute(0, 1, 3, 2, 4, 5).reshape(-1, n, n, c)
            y = self.attn(y)
            y = y.view(b, gh, gw, n, n, c).permute(0, 1, 3, 2, 4, 5).reshape(b, gh * n, gw * n, c)[:, :h, :w]
        else:
            y = self.attn(y)
        x = x + y
        return x + self.mlp(self.norm2(x))


class PatchEmbed(nn.Module):
    """``proj``: the 16x16 stride-16 patch convolution, output channels last."""

    def __init__(self, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, SAM_PATCH, SAM_PATCH)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).permute(0, 2, 3, 1)


def neck(dim: int) -> nn.Sequential:
    """The encoder's ``neck``: [B, dim, 64, 64] -> [B, 256, 64, 64] by a 1x1 and a 3x3 convolution
    (bias-free), each followed by a channel LayerNorm (MobileSAM's TinyViT ends in the same)."""
    return nn.Sequential(nn.Conv2d(dim, EMBED_CHANNELS, 1, bias=False), LayerNorm2d(EMBED_CHANNELS),
                         nn.Conv2d(EMBED_CHANNELS, EMBED_CHANNELS, 3, padding=1, bias=False),
                         LayerNorm2d(EMBED_CHANNELS))


class ImageEncoder(nn.Module):
    """SAM's ViT image encoder: [B, 3, 1024, 1024] normalised pixels -> [B, 256, 64, 64]."""

    def __init__(self, dim: int, depth: int, heads: int, global_blocks: tuple[int, ...]):
        super().__init__()
        grid = SAM_IMAGE_SIZE // SAM_PATCH
        self.patch_embed = PatchEmbed(dim)
        self.pos_embed = nn.Parameter(torch.zeros(1, grid, grid, dim))
        self.blocks = nn.ModuleList(EncoderBlock(dim, heads, 0 if i in global_blocks else WINDOW, grid)
                                    for i in range(depth))
        self.neck = neck(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.patch_embed(x) + self.pos_embed
        for block in self.blocks:
            x = block(x)
        return self.neck(x.permute(0, 3, 1, 2))
