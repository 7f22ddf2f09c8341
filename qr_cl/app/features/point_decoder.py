"""SAM's mask decoder for many single-point prompts on one image: the maths of
:class:`~.sam_decoder.MaskDecoder` (its readable reference, which the tests compare against),
rearranged so that the work on the 64x64 image tokens is done once per image where it can be and
is otherwise pushed onto the 7 prompt tokens.

With ``X`` an [N, C] map of image tokens (N = 4096, C = 256) and ``t`` the 7 tokens of one prompt,
each attention head h (8 heads of width d) of the decoder's cross-attentions becomes:

- tokens -> image: the logits ``(t Wq_h + bq_h)(X Wk_h + bk_h)^T`` equal ``(t Wq_h Wk_h^T) X^T``
  plus a constant per token, which the softmax ignores; the values ``P (X Wv_h + bv_h)`` equal
  ``(P X) Wv_h + bv_h`` (softmax rows sum to 1): [7, C] x [C, N] products instead of projecting
  the whole map. In the first block ``X`` is the same for every prompt: its keys and values are
  projected once per image.
- image -> tokens: the logits ``(X Wq_h + bq_h) K_h^T`` equal ``X (Wq_h K_h^T) + bq_h K_h^T``, and
  the output projection folds into the token values (``V_h Wo_h``, its bias spread over the
  heads, whose weights sum to 1 each): the update of the map is ``P^T V``, [N, 8*7] x [8*7, C].
  In the first block ``X Wq_h`` is once per image.
- The first upscaling convolution (2x2, stride 2: a per-token [C, 4*64] map) is linear, and the
  map it reads is ``LN2(LN1(X0 + P1^T V1) + P2^T V2)``. A LayerNorm is ``(x - mean) * rstd``
  per token, then a gain and bias per channel, so the convolution of the final map is
  ``rstd2 * (rstd1 * ((X0 W'' + P1^T V1 W'') - mean1 c1) + b1 W' + P2^T V2 W' - mean2 c2) + b2 W + bias``
  (``W' = diag(g2) W``, ``W'' = diag(g1) W'``, ``c`` their column sums): ``X0 W''`` once per
  image, then two [N, 8*7+1] x [8*7+1, 256] products per prompt instead of [N, C] x [C, 256].
- The second convolution is per pixel too ([64] -> [2*2*32] channels last); the masks stay in
  that sub-pixel order until the last reshape. Only the three multimask outputs are decoded
  (the single-mask output is never used; the last attention runs for the four output tokens that
  are read), only for the token rows and columns the caller's crop reads, and only for the
  prompts asked for.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .sam_decoder import MaskDecoder, TokenAttention

#: The decoder's outputs kept: the three multimask outputs (index 0 is the single-mask output).
MULTIMASK = (1, 2, 3)
#: The output tokens read after the transformer: the IoU token and the kept outputs' mask tokens.
READ_TOKENS = (0,) + tuple(1 + i for i in MULTIMASK)
#: Low-resolution mask logits per image token and axis (two 2x upscaling convolutions).
UPSCALE = 4
#: Image tokens upscaled at a time (a tile's temporaries stay in the CPU's caches).
TOKEN_TILE = 256


def _split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """[..., T, heads * d] -> [..., heads, T, d]."""
    return x.unflatten(-1, (heads, -1)).transpose(-3, -2)


def _head_weights(linear: torch.nn.Linear, heads: int) -> torch.Tensor:
    """[heads, d, C_in]: ``linear``'s weight rows per head."""
    return linear.weight.unflatten(0, (heads, -1))


def _layer_norm(norm: torch.nn.LayerNorm, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(``norm(x)``, mean [..., 1], rstd [..., 1]) of ``x`` [..., C]."""
    return torch.native_layer_norm(x, norm.normalized_shape, norm.weight, norm.bias, norm.eps)


def _tokens_to_image(attn: TokenAttention, queries: torch.Tensor, image_pe: torch.Tensor,
                     image: torch.Tensor) -> torch.Tensor:
    """[B, T, C]: ``attn(queries, image_pe, image)`` for ``queries`` [B, T, C], keys from
    ``image_pe`` and values from ``image`` [B, N, C], projections on the tokens' side."""
    heads = attn.heads
    q = _split_heads(attn.q_proj(queries), heads)                                    # [B, h, T, d]
    folded = (q @ _head_weights(attn.k_proj, heads)).flatten(1, 2)                   # [B, h*T, C]
    scale = 1 / math.sqrt(q.shape[-1])
    weights = torch.softmax((folded @ image_pe.transpose(1, 2)) * scale, -1)         # [B, h*T, N]
    pooled = (weights @ image).unflatten(1, (heads, -1))                             # [B, h, T, C]
    values = pooled @ _head_weights(attn.v_proj, heads).transpose(1, 2) + attn.v_proj.bias.view(heads, 1, -1)
    return attn.out_proj(values.transpose(1, 2).flatten(2))


@dataclass
class MapUpdate:
    """One image -> tokens update of the image map, ``x + weights^T @ values``: ``weights``
    [B, h*T, N] (each head's softmax over its T tokens), ``values`` [B, h*T, C] (output projection
    and bias folded in); ``mean``, ``rstd`` [B, N, 1] of the LayerNorm that follows."""

    weights: torch.Tensor
    values: torch.Tensor
    mean: torch.Tensor | None = None
    rstd: torch.Tensor | None = None


def _image_update(attn: TokenAttention, logits: torch.Tensor, tokens: torch.Tensor) -> MapUpdate:
    """The update by ``attn`` from the image to the tokens, given the image queries' logits
    ``logits`` [B, h, T, N] (before scaling) and the tokens ``tokens`` [B, T, C] the values come
    from."""
    heads = attn.heads
    scale = 1 / math.sqrt(attn.q_proj.out_features // heads)
    weights = torch.softmax(logits * scale, 2).flatten(1, 2)                         # [B, h*T, N]
    out = attn.out_proj.weight.T.unflatten(0, (heads, -1))                           # [h, d, C]
    values = _split_heads(attn.v_proj(tokens), heads) @ out + attn.out_proj.bias / heads
    return MapUpdate(weights, values.flatten(1, 2))


def _apply(update: MapUpdate, x: torch.Tensor, norm: torch.nn.LayerNorm) -> torch.Tensor:
    """``norm(x + update)`` for ``x`` [B or 1, N, C]; keeps the norm's statistics in ``update``."""
    y, update.mean, update.rstd = _layer_norm(norm, torch.baddbmm(x, update.weights.transpose(1, 2), update.values))
    return y


@dataclass
class PromptTokens:
    """What the transformer leaves for the masks of B prompts: ``hs`` [B, 4, C] the output tokens
    of :data:`READ_TOKENS`; ``first``, ``second`` the two blocks' updates of the image map (their
    norms' statistics included)."""

    hs: torch.Tensor
    first: MapUpdate
    second: MapUpdate

    def take(self, index: torch.Tensor) -> "PromptTokens":
        """The prompts at ``index``."""
        return PromptTokens(self.hs[index], *(MapUpdate(u.weights[index], u.values[index], u.mean[index],
                                                        u.rstd[index]) for u in (self.first, self.second)))


class PointDecoder:
    """The decoder of one image embedding ``image`` [1, C, 64, 64] with positions ``image_pe``
    [1, C, 64, 64] and the dense prompt ``dense`` [1, C, 1, 1] (no mask): the image-side work made
    once (module docstring)."""

    def __init__(self, decoder: MaskDecoder, image: torch.Tensor, image_pe: torch.Tensor, dense: torch.Tensor):
        self.decoder = decoder
        self.grid = image.shape[-1]
        first, second = decoder.transformer.layers
        conv = decoder.output_upscaling[0]
        with torch.no_grad():
            self.keys = (image + dense).flatten(2).transpose(1, 2)                    # [1, N, C]
            self.pe = image_pe.flatten(2).transpose(1, 2)                             # [1, N, C]
            keys_pe = self.keys + self.pe
            t2i, i2t = first.cross_attn_token_to_image, first.cross_attn_image_to_token
            self.first_k = _split_heads(t2i.k_proj(keys_pe), t2i.heads)               # [1, h, N, d]
            self.first_v = _split_heads(t2i.v_proj(self.keys), t2i.heads)
            self.first_q = _split_heads(i2t.q_proj(keys_pe), i2t.heads).transpose(-1, -2)   # [1, h, d, N]
            w = conv.weight.permute(0, 2, 3, 1).flatten(1)                            # [C, 2*2*64] channels last
            self.conv_w2 = second.norm4.weight[:, None] * w                           # W'
            self.conv_w1 = first.norm4.weight[:, None] * self.conv_w2                 # W''
            self.conv_b1 = first.norm4.bias @ self.conv_w2
            self.conv_b2 = second.norm4.bias @ w + conv.bias.repeat(4)
            self.keys_conv = self.keys @ self.conv_w1                                 # X0 W'' [1, N, 256]
            conv2 = decoder.output_upscaling[3]
            self.up2_w = conv2.weight.permute(0, 2, 3, 1).flatten(1)                # [64, 2*2*32] channels last
            self.up2_b = conv2.bias.repeat(4)

    def transform(self, sparse: torch.Tensor) -> PromptTokens:
        """The two-way transformer (:class:`~.sam_decoder.TwoWayTransformer`) of the decoder's
        tokens and the prompts ``sparse`` [B, T - 5, C] on the image."""
        dec = self.decoder
        b = len(sparse)
        out_tokens = torch.cat([dec.iou_token.weight, dec.mask_tokens.weight], 0).expand(b, -1, -1)
        tokens = torch.cat([out_tokens, sparse], 1)
        first, second = dec.transformer.layers
        with torch.no_grad():
            queries = first.norm1(first.self_attn(tokens, tokens, tokens))
            t2i = first.cross_attn_token_to_image
            q = _split_heads(t2i.q_proj(queries + tokens), t2i.heads)
            attended = F.scaled_dot_product_attention(q, self.first_k.expand(b, -1, -1, -1),
                                                      self.first_v.expand(b, -1, -1, -1))
            queries = first.norm2(queries + t2i.out_proj(attended.transpose(1, 2).flatten(2)))
            queries = first.norm3(queries + first.mlp(queries))
            i2t = first.cross_attn_image_to_token
            k = _split_heads(i2t.k_proj(queries + tokens), i2t.heads)                # [B, h, T, d]
            first_update = _image_update(i2t, k @ self.first_q, queries)
            keys = _apply(first_update, self.keys, first.norm4)

            q = queries + tokens
            queries = second.norm1(queries + second.self_attn(q, q, queries))
            keys_pe = keys + self.pe
            queries = second.norm2(queries + _tokens_to_image(second.cross_attn_token_to_image, queries + tokens,
                                                             keys_pe, keys))
            queries = second.norm3(queries + second.mlp(queries))
            i2t = second.cross_attn_image_to_token
            k = _split_heads(i2t.k_proj(queries + tokens), i2t.heads)                # [B, h, T, d]
            folded = k @ _head_weights(i2t.q_proj, i2t.heads)                        # [B, h, T, C]
            bias = k @ i2t.q_proj.bias.view(i2t.heads, -1, 1)                        # [B, h, T, 1]
            logits = (folded.flatten(1, 2) @ keys_pe.transpose(1, 2)).unflatten(1, (i2t.heads, -1)) + bias
            second_update = _image_update(i2t, logits, queries)
            keys = _apply(second_update, keys, second.norm4)

            final = dec.transformer.final_attn_token_to_image
            read = list(READ_TOKENS)                                                  # the last attention's other
            queries, tokens = queries[:, read], tokens[:, read]                       # outputs are never read
            queries = queries + _tokens_to_image(final, queries + tokens, keys + self.pe, keys)
            return PromptTokens(dec.transformer.norm_final_attn(queries), first_update, second_update)

    def iou(self, tokens: PromptTokens) -> torch.Tensor:
        """[B, 3] predicted IoU of the multimask outputs."""
        with torch.no_grad():
            return self.decoder.iou_prediction_head(tokens.hs[:, 0])[:, list(MULTIMASK)]

    def masks(self, tokens: PromptTokens, rows: int | None = None, cols: int | None = None) -> torch.Tensor:
        """[B, 3, UPSCALE * rows, UPSCALE * cols] mask logits of the multimask outputs over the first ``rows``
        x ``cols`` image tokens (all by default; the logits of SAM's [256, 256] grid there)."""
        dec = self.decoder
        g = self.grid
        rows, cols = rows or g, cols or g
        norm = dec.output_upscaling[1]
        b = len(tokens.hs)

        def window(x: torch.Tensor) -> torch.Tensor:                                 # [B, N, k] -> its window
            return x.unflatten(1, (g, g))[:, :rows, :cols].flatten(1, 2)

        def augmented(update: MapUpdate, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            a = torch.cat([window(update.weights.transpose(1, 2)), -window(update.mean)], -1)   # [B, n, h*T + 1]
            return a, torch.cat([update.values @ w, w.sum(0).expand(b, 1, -1)], 1)          # [B, h*T + 1, 256]

        with torch.no_grad():
            mlps = dec.output_hypernetworks_mlps
            hyper = torch.stack([mlps[i](tokens.hs[:, 1 + k]) for k, i in enumerate(MULTIMASK)], 2)  # [B, 32, 3]
            first, first_values = augmented(tokens.first, self.conv_w1)
            second, second_values = augmented(tokens.second, self.conv_w2)
            keys, rstd1, rstd2 = window(self.keys_conv), window(tokens.first.rstd), window(tokens.second.rstd)
            low = []
            for t in range(0, keys.shape[1], TOKEN_TILE):                             # per token: tiles stay in cache
                part = slice(t, t + TOKEN_TILE)
                up = torch.baddbmm(keys[:, part], first[:, part], first_values)
                up = torch.addcmul(self.conv_b1, up, rstd1[:, part]).baddbmm_(second[:, part], second_values)
                up = torch.addcmul(self.conv_b2, up, rstd2[:, part]).unflatten(-1, (4, -1))   # [B, tile, 4, 64]
                up = F.gelu(F.layer_norm(up, up.shape[-1:], norm.weight, norm.bias, norm.eps))
                up = F.gelu((up @ self.up2_w).add_(self.up2_b))         # [B, tile, 4, 4*32]
                low.append(up.flatten(1, 2).unflatten(-1, (4, -1)).flatten(1, 2) @ hyper)   # [B, tile*16, 3]
            low = torch.cat(low, 1)
        low = low.view(b, rows, cols, 2, 2, 2, 2, len(MULTIMASK))                     # i, j, a, c, a2, c2
        return low.permute(0, 7, 1, 3, 5, 2, 4, 6).reshape(b, len(MULTIMASK), UPSCALE * rows, UPSCALE * cols)
