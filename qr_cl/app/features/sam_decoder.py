"""SAM's prompt encoder (points only) and mask decoder in plain torch, under the official
checkpoints' names (``prompt_encoder.*``, ``mask_decoder.*``).

Points are embedded by random Fourier features of their position (a fixed Gaussian matrix) plus
a learned embedding of their label; a padding point (label -1) follows when no box is given. The
decoder is a two-way transformer of two blocks (tokens' self-attention, tokens -> image and
image -> tokens cross-attention at half width, a ReLU MLP) and a last tokens -> image attention,
then the image is upscaled 4x by two transposed convolutions and each of the four mask tokens
becomes, through its own 3-layer MLP, the weights of a dot product with every upscaled pixel. An
IoU token's MLP predicts each mask's quality. :class:`MaskDecoder` is the decoder as published,
one prompt's maths at a time: the readable reference of :mod:`.point_decoder`, which decodes
``qr-cl features``' prompts.
"""
from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from .sam_encoder import EMBED_CHANNELS, SAM_IMAGE_SIZE, LayerNorm2d

#: Masks the decoder predicts per prompt (one single-mask output and three multimask outputs).
MASK_TOKENS = 4


class FourierPositions(nn.Module):
    """``positional_encoding_gaussian_matrix`` [2, 128]: (x, y) in [0, 1] -> [sin, cos] of
    2 pi (2 xy - 1) G, 256 channels."""

    def __init__(self, features: int = EMBED_CHANNELS // 2):
        super().__init__()
        self.register_buffer("positional_encoding_gaussian_matrix", torch.randn(2, features))

    def encode(self, unit_xy: torch.Tensor) -> torch.Tensor:
        """[..., 256] encodings of [..., 2] coordinates in [0, 1]."""
        x = 2 * math.pi * ((2 * unit_xy - 1) @ self.positional_encoding_gaussian_matrix)
        return torch.cat([torch.sin(x), torch.cos(x)], -1)

    def grid(self, size: int) -> torch.Tensor:
        """[256, size, size] encodings of the centres of a size x size grid."""
        centres = (torch.arange(size, dtype=torch.float32, device=self.positional_encoding_gaussian_matrix.device) + 0.5) / size
        xy = torch.stack([centres[None, :].expand(size, size), centres[:, None].expand(size, size)], -1)
        return self.encode(xy).permute(2, 0, 1)


class PromptEncoder(nn.Module):
    """Point prompts -> sparse embeddings; the dense embedding is ``no_mask_embed`` (no mask
    prompt). ``mask_downscaling`` is kept for the checkpoint's names only (mask prompts are not
    used here)."""

    def __init__(self):
        super().__init__()
        c = EMBED_CHANNELS
        self.pe_layer = FourierPositions()
        self.point_embeddings = nn.ModuleList(nn.Embedding(1, c) for _ in range(4))
        self.not_a_point_embed = nn.Embedding(1, c)
        self.mask_downscaling = nn.Sequential(nn.Conv2d(1, 4, 2, 2), LayerNorm2d(4), nn.GELU(), nn.Conv2d(4, 16, 2, 2),
                                              LayerNorm2d(16), nn.GELU(), nn.Conv2d(16, c, 1))
        self.no_mask_embed = nn.Embedding(1, c)

    def embed_points(self, points: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
        """[B, N + 1, 256] embeddings of ``points`` [B, N, 2] (px in the 1024 input) with ``labels``
        [B, N] (1 foreground, 0 background), a padding point appended."""
        points = torch.cat([points + 0.5, torch.zeros_like(points[:, :1])], 1)
        labels = torch.cat([labels, -torch.ones_like(labels[:, :1])], 1)
        emb = self.pe_layer.encode(points / SAM_IMAGE_SIZE)
        emb = torch.where((labels == -1)[..., None], self.not_a_point_embed.weight, emb)
        for value in (0, 1):
            emb = emb + (labels == value)[..., None] * self.point_embeddings[value].weight
        return emb


class TokenAttention(nn.Module):
    """Attention with separate ``q_proj``/``k_proj``/``v_proj`` to ``dim // downsample``
    channels and ``out_proj`` back."""

    def __init__(self, dim: int, heads: int, downsample: int = 1):
        super().__init__()
        inner = dim // downsample
        self.heads = heads
        self.q_proj, self.k_proj, self.v_proj = nn.Linear(dim, inner), nn.Linear(dim, inner), nn.Linear(dim, inner)
        self.out_proj = nn.Linear(inner, dim)

    def forward(self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        def split(x):
            return x.view(x.shape[0], x.shape[1], self.heads, -1).transpose(1, 2)
        y = F.scaled_dot_product_attention(split(self.q_proj(q)), split(self.k_proj(k)), split(self.v_proj(v)))
        return self.out_proj(y.transpose(1, 2).flatten(2))


class ReluMlp(nn.Module):
    """``lin1`` -> ReLU -> ``lin2``."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.lin1, self.lin2 = nn.Linear(dim, hidden), nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.lin2(F.relu(self.lin1(x)))


class TwoWayBlock(nn.Module):
    """Tokens' self-attention, tokens -> image, MLP, image -> tokens (module docstring)."""

    def __init__(self, dim: int, heads: int, hidden: int, first: bool):
        super().__init__()
        self.first = first
        self.self_attn = TokenAttention(dim, heads)
        self.cross_attn_token_to_image = TokenAttention(dim, heads, 2)
        self.cross_attn_image_to_token = TokenAttention(dim, heads, 2)
        self.mlp = ReluMlp(dim, hidden)
        self.norm1, self.norm2, self.norm3, self.norm4 = (nn.LayerNorm(dim) for _ in range(4))

    def forward(self, queries, keys, query_pe, key_pe):
        if self.first:
            queries = self.self_attn(queries, queries, queries)
        else:
            q = queries + query_pe
            queries = queries + self.self_attn(q, q, queries)
        queries = self.norm1(queries)
        queries = self.norm2(queries + self.cross_attn_token_to_image(queries + query_pe, keys + key_pe, keys))
        queries = self.norm3(queries + self.mlp(queries))
        keys = self.norm4(keys + self.cross_attn_image_to_token(keys + key_pe, queries + query_pe, queries))
        return queries, keys


class TwoWayTransformer(nn.Module):
    """``layers`` (two :class:`TwoWayBlock`), ``final_attn_token_to_image``, ``norm_final_attn``."""

    def __init__(self, dim: int = EMBED_CHANNELS, heads: int = 8, hidden: int = 2048, depth: int = 2):
        super().__init__()
        self.layers = nn.ModuleList(TwoWayBlock(dim, heads, hidden, i == 0) for i in range(depth))
        self.final_attn_token_to_image = TokenAttention(dim, heads, 2)
        self.norm_final_attn = nn.LayerNorm(dim)

    def forward(self, image: torch.Tensor, image_pe: torch.Tensor, tokens: torch.Tensor):
        """(tokens [B, T, C], image tokens [B, HW, C]) after the transformer; ``image`` and
        ``image_pe`` are [B, C, H, W]."""
        keys, key_pe = image.flatten(2).transpose(1, 2), image_pe.flatten(2).transpose(1, 2)
        queries = tokens
        for layer in self.layers:
            queries, keys = layer(queries, keys, tokens, key_pe)
        queries = queries + self.final_attn_token_to_image(queries + tokens, keys + key_pe, keys)
        return self.norm_final_attn(queries), keys


class HeadMlp(nn.Module):
    """``layers``: Linear layers with ReLU between them."""

    def __init__(self, dims: list[int]):
        super().__init__()
        self.layers = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:]))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        for i, layer in enumerate(self.layers):
            x = layer(x) if i == len(self.layers) - 1 else F.relu(layer(x))
        return x


class MaskDecoder(nn.Module):
    """SAM's mask decoder (module docstring)."""

    def __init__(self):
        super().__init__()
        c = EMBED_CHANNELS
        self.transformer = TwoWayTransformer()
        self.iou_token = nn.Embedding(1, c)
        self.mask_tokens = nn.Embedding(MASK_TOKENS, c)
        self.output_upscaling = nn.Sequential(nn.ConvTranspose2d(c, c // 4, 2, 2), LayerNorm2d(c // 4), nn.GELU(),
                                              nn.ConvTranspose2d(c // 4, c // 8, 2, 2), nn.GELU())
        self.output_hypernetworks_mlps = nn.ModuleList(HeadMlp([c, c, c, c // 8]) for _ in range(MASK_TOKENS))
        self.iou_prediction_head = HeadMlp([c, 256, 256, MASK_TOKENS])

    def forward(self, image: torch.Tensor, image_pe: torch.Tensor, sparse: torch.Tensor, dense: torch.Tensor):
        """(mask logits [B, 4, 256, 256], predicted IoU [B, 4]) for prompts ``sparse`` [B, T, C]
        and ``dense`` [B, C, 64, 64] on one ``image`` embedding [1, C, 64, 64] with positions
        ``image_pe`` [1, C, 64, 64]."""
        b = len(sparse)
        out_tokens = torch.cat([self.iou_token.weight, self.mask_tokens.weight], 0).expand(b, -1, -1)
        tokens = torch.cat([out_tokens, sparse], 1)
        src = image.expand(b, -1, -1, -1) + dense
        hs, src = self.transformer(src, image_pe.expand(b, -1, -1, -1), tokens)
        grid = image.shape[-1]
        up = self.output_upscaling(src.transpose(1, 2).reshape(b, -1, grid, grid))
        hyper = torch.stack([mlp(hs[:, 1 + i]) for i, mlp in enumerate(self.output_hypernetworks_mlps)], 1)
        masks = (hyper @ up.flatten(2)).view(b, MASK_TOKENS, *up.shape[-2:])
        return masks, self.iou_prediction_head(hs[:, 0])

