"""SAM's mask decoder for many single-point prompts on one image: the maths of
:class:`~.sam_decoder.MaskDecoder` (its readable reference, which the tests compare against),
rearranged so that the work on the 64x64 image tokens is done once per image where it can be and
is otherwise pushed onto the 7 prompt tokens.

With ``X0`` the [N, C] map of image tokens (N = 4096, C = 256), 7 tokens per prompt and
cross-attentions of 8 heads of width d = 16:

- Block one: its tokens -> image attention reads the image map before any prompt changed it, so
  its keys, values and image queries are projected once per image, and all prompts' queries
  attend to it as one sequence per head.
- After block one's image -> tokens update the map is ``LN1(X0 + a1^T V1)``: a1 [8*7, N] the
  attention weights (each head's softmax over its 7 tokens), V1 [8*7, C] the token values with the
  output projection folded in. Written as ``rstd1 * (Y + a1^T R1) + b1`` (Y = (X0 - mean) * g1,
  the same for every prompt; R1 the centred values times g1), a projection ``W`` of it per head is
  ``rstd1 * (Y W + a1^T (R1 W)) + b1 W``: ``Y W`` once per image, then a [N, 56] x [56, d] product
  per prompt; attention logits and pooled values reduce further to [56, 56] x [56, N] products
  (:class:`LowRankMap`). After block two the map is ``LN2(X1 + a2^T V2)``, one more such term.
- The norms' statistics come from the same factors: the squared norm of ``(X0 - mean) + a1^T Vc``
  is ``|X0 - mean|^2 + 2 a1 . ((X0 - mean) . V1) + a1 . (Vc Vc^T a1)``, the middle products per
  head through ``(X0 - mean) Wo`` made once per image (V1 = values Wo + bias); block two's the same
  with three [56, 56] forms (:meth:`PointDecoder._second_norm`). No [N, C] map is ever formed.
- The first upscaling convolution (2x2, stride 2: a per-token [C, 4*64] map) is linear, and the
  map it reads is ``LN2(LN1(X0 + a1^T V1) + a2^T V2)``. A LayerNorm is ``(x - mean) * rstd``
  per token, then a gain and bias per channel, so the convolution of the final map is
  ``rstd2 * (rstd1 * ((X0 W'' + a1^T V1 W'') - mean1 c1) + b1 W' + a2^T V2 W' - mean2 c2) + b2 W + bias``
  (``W' = diag(g2) W``, ``W'' = diag(g1) W'``, ``c`` their column sums): ``X0 W''`` once per
  image, then ``rstd1 rstd2 (X0 W'')`` plus ``b2 W + bias`` and one [N, 2*(8*7+1)+1] x
  [2*(8*7+1)+1, 256] product per prompt (the rows ``V1 W''``, ``c1``, ``V2 W'``, ``c2``, ``b1 W'``
  with their coefficients times ``rstd2``) instead of [N, C] x [C, 256].
- The second convolution is per pixel too ([64] -> [2*2*32] channels last); the hypernetwork
  reads its 32 channels per output pixel as a [3, 32] x [32, pixels] product per prompt, and each
  tile's masks are gathered from that sub-pixel order into the output's (:func:`_grid_order`).
  Only the three multimask outputs are decoded (the single-mask output is never used; the last
  attention runs for the four output tokens that are read), only for the token rows and columns
  the caller's crop reads, and only for the prompts asked for.
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
#: Image tokens times prompts upscaled at a time (a tile's temporaries stay in the CPU's caches).
TOKEN_TILE = 4096


def _split_heads(x: torch.Tensor, heads: int) -> torch.Tensor:
    """[..., T, heads * d] -> [..., heads, T, d]."""
    return x.unflatten(-1, (heads, -1)).transpose(-3, -2)


def _head_scores(q: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """[h, B, T, N]: per head the products ``q`` [B, h, T, d] x ``rows`` [h, N, d]^T, as h products
    of all B*T queries (``rows`` read once per head, not once per prompt), heads first."""
    b, heads, t, d = q.shape
    return (q.transpose(0, 1).reshape(heads, b * t, d) @ rows.transpose(1, 2)).view(heads, b, t, -1)


def _add_heads(out: torch.Tensor, scores: torch.Tensor, scale: torch.Tensor | None = None) -> torch.Tensor:
    """``out`` [B, h*T, N] plus ``scores`` [h, B, T, N] (:func:`_head_scores`), times ``scale``
    [B, 1, N] if given; in place."""
    view = out.view(len(out), scores.shape[0], scores.shape[2], -1)
    heads = scores.permute(1, 0, 2, 3)
    if scale is None:
        view.add_(heads)
    else:
        view.addcmul_(heads, scale[:, :, None])
    return out


def _grid_order(rows: int, cols: int, device: torch.device) -> torch.Tensor:
    """[rows * cols * 16] int64: for each logit of ``rows`` x ``cols`` image tokens in the mask
    grid's order (token row i, first and second convolution's sub-pixel rows a, a2, token column
    j, their sub-pixel columns c, c2), its place in the upscaling's order (i, j, a, c, a2, c2).
    A gather by it is one pass; a copy through the 8-dimensional permuted view was ten times slower."""
    upscaled = torch.arange(rows * cols * UPSCALE ** 2, device=device).view(rows, cols, 2, 2, 2, 2)
    return upscaled.permute(0, 2, 4, 1, 3, 5).flatten()


def _gelu_(x: torch.Tensor) -> torch.Tensor:
    """``x`` through the exact (erf) GELU, in place."""
    return torch.ops.aten.gelu_(x)


def _dot(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """[B, 1, N]: sum over k of ``x`` [B, k, N] times ``y`` [B, k, N] (``y`` is overwritten)."""
    return y.mul_(x).sum(1, keepdim=True)


@dataclass(frozen=True)
class Projected:
    """One attention projection (``linear``, its weight [h*d, C]) of the maps of a
    :class:`LowRankMap`, per head: ``image`` [h, N, d] the projection of its shared rows (no
    bias), ``const`` [h, N or 1, d] that of what is added to the map (positions, the norm's bias)
    with the projection's bias."""

    weight: torch.Tensor
    image: torch.Tensor
    const: torch.Tensor

    @staticmethod
    def of(linear: torch.nn.Linear, heads: int, image: torch.Tensor, const: torch.Tensor) -> "Projected":
        """The projection by ``linear`` of ``image`` [N, C] and ``const`` [N or 1, C]."""
        return Projected(linear.weight, _split_heads(image @ linear.weight.T, heads),
                         _split_heads(linear(const), heads))

    def rows(self, rows: torch.Tensor) -> torch.Tensor:
        """[..., h, k, d]: ``rows`` [..., k, C] projected (no bias)."""
        return _split_heads(rows @ self.weight.T, self.image.shape[0])


@dataclass(frozen=True)
class LowRankMap:
    """B prompts' image maps after a LayerNorm (before its bias), never formed:
    ``rstd * (inner + coeffs^T rows + offset)``, ``inner`` another such map or, when None, the
    [N, C] rows ``Y`` that all prompts share (their projections are a :class:`Projected`'s).
    ``rstd`` [B, 1, N] per token, ``coeffs`` [B, k, N] and ``rows`` [B, k, C] (k = 8*7: an
    update's attention weights and values), ``offset`` [C] or None. Attention logits and pooled
    values of a projection cost [N, k] x [k, h*T] products instead of [N, C] ones."""

    rstd: torch.Tensor
    coeffs: torch.Tensor
    rows: torch.Tensor
    inner: "LowRankMap | None" = None
    offset: torch.Tensor | None = None

    def logits(self, q: torch.Tensor, proj: Projected) -> torch.Tensor:
        """[B, h*T, N]: ``q`` [B, h, T, d] against the maps projected by ``proj``, per head."""
        folded = (proj.rows(self.rows) @ q.transpose(2, 3)).transpose(2, 3).flatten(1, 2)   # [B, h*T, k]
        out = folded @ self.coeffs
        if self.inner is None:
            _add_heads(out, _head_scores(q, proj.image))
        else:
            out.add_(self.inner.logits(q, proj))
        if self.offset is not None:
            out.add_((q @ proj.rows(self.offset[None]).transpose(1, 2)).flatten(1, 2))
        return out.mul_(self.rstd)

    def pooled(self, weights: torch.Tensor, proj: Projected) -> torch.Tensor:
        """[B, h, T, d]: the maps projected by ``proj`` pooled by ``weights`` [B, h*T, N]."""
        b, heads = len(weights), proj.image.shape[0]
        scaled = weights * self.rstd
        out = (scaled @ self.coeffs.transpose(1, 2)).unflatten(1, (heads, -1)) @ proj.rows(self.rows)
        if self.inner is None:
            image = scaled.view(b, heads, -1, scaled.shape[-1]).transpose(0, 1).flatten(1, 2) @ proj.image
            out.add_(image.view(heads, b, -1, image.shape[-1]).transpose(0, 1))
        else:
            out.add_(self.inner.pooled(scaled, proj))
        if self.offset is not None:
            out.addcmul_(scaled.sum(-1).unflatten(1, (heads, -1))[..., None], proj.rows(self.offset[None]))
        return out


@dataclass
class MapUpdate:
    """One image -> tokens update of the image map, ``x + weights^T @ values``: ``weights``
    [B, h*T, N] (each head's softmax over its T tokens), ``values`` [B, h*T, C] (output projection
    and bias folded in); ``mean``, ``rstd`` [B, N, 1] of the LayerNorm that follows;
    ``heads`` [B, h, T, d] the values before the output projection."""

    weights: torch.Tensor
    values: torch.Tensor
    mean: torch.Tensor | None = None
    rstd: torch.Tensor | None = None
    heads: torch.Tensor | None = None


def _scaled_heads(linear: torch.nn.Linear, x: torch.Tensor, heads: int) -> torch.Tensor:
    """[B, h, T, d]: ``linear`` of ``x`` [B, T, C] per head, times attention's 1 / sqrt(d): logits
    against it come scaled, with no pass over them."""
    out = _split_heads(linear(x), heads)
    return out.mul_(1 / math.sqrt(out.shape[-1]))


def _image_update(attn: TokenAttention, logits: torch.Tensor, tokens: torch.Tensor) -> MapUpdate:
    """The update by ``attn`` from the image to the tokens, given the image queries' logits
    ``logits`` [B, h, T, N] (scaled) and the tokens ``tokens`` [B, T, C] the values come from."""
    heads = attn.heads
    weights = torch.softmax(logits, 2).flatten(1, 2)                                 # [B, h*T, N]
    out = attn.out_proj.weight.T.unflatten(0, (heads, -1))                           # [h, d, C]
    per_head = _split_heads(attn.v_proj(tokens), heads)
    values = per_head @ out + attn.out_proj.bias / heads
    return MapUpdate(weights, values.flatten(1, 2), heads=per_head)


def _rstd(squares: torch.Tensor, norm: torch.nn.LayerNorm) -> torch.Tensor:
    """[B, 1, N]: ``norm``'s 1 / std of tokens whose centred squares sum to ``squares``."""
    return torch.rsqrt(squares.clamp_min(0) / norm.normalized_shape[0] + norm.eps)


def _gram(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """[B, k, l]: the dot products of the rows of ``x`` [B, k, C] and ``y`` [B, l, C]."""
    return x @ y.transpose(1, 2)


def _centred(x: torch.Tensor) -> torch.Tensor:
    """``x`` [..., C] less its mean over C."""
    return x - x.mean(-1, keepdim=True)


def _map_logits(image: LowRankMap, q: torch.Tensor, proj: Projected) -> torch.Tensor:
    """[B, h*T, N]: ``q`` [B, h, T, d] against the maps ``image`` projected by ``proj``, what is
    added to them included."""
    return _add_heads(image.logits(q, proj), _head_scores(q, proj.const))


def _attend(attn: TokenAttention, queries: torch.Tensor, image: LowRankMap, keys: Projected,
            values: Projected) -> torch.Tensor:
    """[B, T, C]: ``attn`` from ``queries`` [B, T, C] to the maps ``image``, whose keys (with
    positions) and values project as ``keys`` and ``values``."""
    q = _scaled_heads(attn.q_proj, queries, attn.heads)                              # [B, h, T, d]
    weights = torch.softmax(_map_logits(image, q, keys), -1)
    return attn.out_proj(image.pooled(weights, values).add_(values.const).transpose(1, 2).flatten(2))


@dataclass
class PromptTokens:
    """What the transformer leaves for the masks of B prompts: ``hs`` [B, 4, C] the output tokens
    of :data:`READ_TOKENS`; ``first``, ``second`` the two blocks' updates of the image map (their
    norms' statistics included)."""

    hs: torch.Tensor
    first: MapUpdate
    second: MapUpdate

    def take(self, index: torch.Tensor) -> "PromptTokens":
        """The prompts at ``index`` (these tokens, not a copy, when ``index`` is a bool mask that
        keeps them all)."""
        if index.dtype == torch.bool and bool(index.all()):
            return self
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
        final = decoder.transformer.final_attn_token_to_image
        conv = decoder.output_upscaling[0]
        with torch.no_grad():
            self.keys = (image + dense).flatten(2).transpose(1, 2)                    # X0 [1, N, C]
            pe = image_pe.flatten(2)[0].T                                             # [N, C]
            keys_pe = self.keys + pe
            t2i, i2t = first.cross_attn_token_to_image, first.cross_attn_image_to_token
            self.first_k = _split_heads(t2i.k_proj(keys_pe), t2i.heads)               # [1, h, N, d]
            self.first_v = _split_heads(t2i.v_proj(self.keys), t2i.heads)
            self.first_q = _split_heads(i2t.q_proj(keys_pe), i2t.heads)[0]            # [h, N, d]
            # the centred map X0 - mean0 and its products with the first update's values
            x0 = self.keys[0]
            self.mean0 = x0.mean(-1)                                                  # [N]
            x0 = x0 - self.mean0[:, None]
            self.squares0 = (x0 * x0).sum(-1)
            self.out0 = _split_heads(x0 @ i2t.out_proj.weight, i2t.heads)             # [h, N, d]
            self.bias0 = x0 @ i2t.out_proj.bias
            # Y = (X0 - mean0) g1, the rows of the map after the first norm that all prompts share
            g1, b1, out1 = first.norm4.weight, first.norm4.bias, i2t.out_proj
            y = x0 * g1
            t2i, i2t = second.cross_attn_token_to_image, second.cross_attn_image_to_token
            self.second_k = Projected.of(t2i.k_proj, t2i.heads, y, pe + b1)
            self.second_v = Projected.of(t2i.v_proj, t2i.heads, y, b1[None])
            self.second_q = Projected.of(i2t.q_proj, i2t.heads, y, pe + b1)
            # Yc = Y - its mean and its products with the updates' values and b1
            self.mean_y = y.mean(-1)
            y = y - self.mean_y[:, None]
            self.squares_y = (y * y).sum(-1)
            self.out_y1 = _split_heads((y * g1) @ out1.weight, i2t.heads)
            self.bias_y1 = (y * g1) @ out1.bias
            self.gain_y1 = y @ g1
            self.out_y2 = _split_heads(y @ i2t.out_proj.weight, i2t.heads)
            self.bias_y2 = y @ (i2t.out_proj.bias + b1)
            g2, b2 = second.norm4.weight, second.norm4.bias
            self.final_k = Projected.of(final.k_proj, final.heads, y * g2, pe + b2)
            self.final_v = Projected.of(final.v_proj, final.heads, y * g2, b2[None])
            w = conv.weight.permute(0, 2, 3, 1).flatten(1)                            # [C, 2*2*64] channels last
            self.conv_w2 = g2[:, None] * w                                            # W'
            self.conv_w1 = g1[:, None] * self.conv_w2                                 # W''
            self.conv_b1 = b1 @ self.conv_w2
            self.conv_b2 = b2 @ w + conv.bias.repeat(4)
            self.keys_conv = self.keys @ self.conv_w1                                 # X0 W'' [1, N, 256]
            conv2 = decoder.output_upscaling[3]
            self.up2_w = conv2.weight.permute(0, 2, 3, 1).flatten(1)                # [64, 2*2*32] channels last
            self.up2_b = conv2.bias.repeat(4)

    def _first_norm(self, update: MapUpdate, norm: torch.nn.LayerNorm) -> LowRankMap:
        """The maps after the first block, ``norm(X0 + a^T V)`` for the update's weights ``a`` and
        values ``V``; sets the update's statistics. The centred map is ``(X0 - mean0) + a^T Vc``
        (``Vc`` the values less their means), whose squares sum to
        ``|X0 - mean0|^2 + 2 a . ((X0 - mean0) . V) + a . (Vc Vc^T a)``."""
        a, values = update.weights, update.values                                    # [B, 56, N], [B, 56, C]
        centred = _centred(values)
        t = _add_heads((0.5 * _gram(centred, centred)) @ a, _head_scores(update.heads, self.out0))
        rstd = _rstd(self.squares0 + 2 * self.bias0 + 2 * _dot(a, t), norm)          # sum over heads of a is 8
        update.rstd = rstd.transpose(1, 2)
        update.mean = (self.mean0 + values.mean(-1)[:, None] @ a).transpose(1, 2)
        return LowRankMap(rstd, a, centred * norm.weight)

    def _second_norm(self, x1: LowRankMap, first: MapUpdate, update: MapUpdate,
                     norm: torch.nn.LayerNorm) -> LowRankMap:
        """The maps after the second block, ``norm(X1 + a2^T V2)`` for the maps ``x1`` after the
        first (``rstd1 (Y + a1^T R1) + b1``) and the update's weights ``a2`` and values ``V2``; sets
        the update's statistics. The centred map is ``rstd1 u + v`` with ``u = Yc + a1^T R1c`` and
        ``v = a2^T V2c + b1c`` (c: less the mean over channels); its squares sum to
        ``rstd1^2 |u|^2 + 2 rstd1 u . v + |v|^2``, each a sum of [56, 56] quadratic forms."""
        b1 = self.decoder.transformer.layers[0].norm4.bias
        a1, a2, rstd1 = first.weights, update.weights, x1.rstd
        rows1, values2, bias1 = _centred(x1.rows), _centred(update.values), _centred(b1)
        mean1 = first.values.mean(-1)[:, None] @ a1                                 # a1 . the values' means
        t = _add_heads((0.5 * _gram(rows1, rows1)) @ a1, _head_scores(first.heads, self.out_y1))
        uu = self.squares_y + 2 * _dot(a1, t) + 2 * (self.bias_y1 - mean1 * self.gain_y1)
        t = _gram(rows1, values2) @ a2 + (rows1 @ bias1)[..., None]
        uv = _dot(a1, t).add_(self.bias_y2)
        t = _add_heads(_gram(values2, values2) @ a2 + 2 * (values2 @ bias1)[..., None],
                       _head_scores(update.heads, self.out_y2), 2 * rstd1)           # and 2 rstd1 (Yc . V2)
        squares = rstd1 ** 2 * uu + 2 * rstd1 * uv + _dot(a2, t) + bias1 @ bias1
        rstd = _rstd(squares, norm)
        update.rstd = rstd.transpose(1, 2)
        mean = rstd1 * (self.mean_y + x1.rows.mean(-1)[:, None] @ a1) + b1.mean() + update.values.mean(-1)[:, None] @ a2
        update.mean = mean.transpose(1, 2)
        g2 = norm.weight
        return LowRankMap(rstd, a2, values2 * g2, LowRankMap(rstd1, a1, rows1 * g2), bias1 * g2)

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
            q = _split_heads(t2i.q_proj(queries + tokens), t2i.heads)                # [B, h, T, d]
            heads, t, d = q.shape[1:]                                                 # every prompt's queries
            attended = F.scaled_dot_product_attention(                                # one sequence per head
                q.transpose(0, 1).reshape(1, heads, b * t, d), self.first_k, self.first_v)
            attended = attended.view(heads, b, t, d).transpose(0, 1)
            queries = first.norm2(queries + t2i.out_proj(attended.transpose(1, 2).flatten(2)))
            queries = first.norm3(queries + first.mlp(queries))
            i2t = first.cross_attn_image_to_token
            k = _scaled_heads(i2t.k_proj, queries + tokens, i2t.heads)               # [B, h, T, d]
            first_update = _image_update(i2t, _head_scores(k, self.first_q).transpose(0, 1), queries)
            x1 = self._first_norm(first_update, first.norm4)

            q = queries + tokens
            queries = second.norm1(queries + second.self_attn(q, q, queries))
            queries = second.norm2(queries + _attend(second.cross_attn_token_to_image, queries + tokens, x1,
                                                     self.second_k, self.second_v))
            queries = second.norm3(queries + second.mlp(queries))
            i2t = second.cross_attn_image_to_token
            k = _scaled_heads(i2t.k_proj, queries + tokens, i2t.heads)               # [B, h, T, d]
            logits = _map_logits(x1, k, self.second_q).unflatten(1, (i2t.heads, -1))
            second_update = _image_update(i2t, logits, queries)
            x2 = self._second_norm(x1, first_update, second_update, second.norm4)

            final = dec.transformer.final_attn_token_to_image
            read = list(READ_TOKENS)                                                  # the last attention's other
            queries, tokens = queries[:, read], tokens[:, read]                       # outputs are never read
            queries = queries + _attend(final, queries + tokens, x2, self.final_k, self.final_v)
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

        def window(x: torch.Tensor) -> torch.Tensor:                                 # [B, k, N] -> [B, k, rows, cols]
            return x.unflatten(2, (g, g))[:, :, :rows, :cols]

        first, second = tokens.first, tokens.second
        with torch.no_grad():
            mlps = dec.output_hypernetworks_mlps
            hyper = torch.stack([mlps[i](tokens.hs[:, 1 + k]) for k, i in enumerate(MULTIMASK)], 1)  # [B, 3, 32]
            rstd2 = window(second.rstd.transpose(1, 2))
            rstd12 = window(first.rstd.transpose(1, 2)) * rstd2
            rank = first.weights.shape[1]                                             # an update's 8*7 terms
            coeffs = rstd2.new_empty(b, 2 * rank + 3, rows, cols)                     # per token, token-minor
            a1, mean1, a2, mean2, bias1 = coeffs.split([rank, 1, rank, 1, 1], 1)
            torch.mul(window(first.weights), rstd12, out=a1)
            torch.mul(window(first.mean.transpose(1, 2)), rstd12, out=mean1).neg_()
            torch.mul(window(second.weights), rstd2, out=a2)
            torch.mul(window(second.mean.transpose(1, 2)), rstd2, out=mean2).neg_()
            bias1.copy_(rstd2)
            coeffs, rstd12 = coeffs.flatten(2), rstd12.flatten(2).transpose(1, 2)     # [B, 115, n], [B, n, 1]
            values = torch.cat([first.values @ self.conv_w1, self.conv_w1.sum(0).expand(b, 1, -1),
                                second.values @ self.conv_w2, self.conv_w2.sum(0).expand(b, 1, -1),
                                self.conv_b1.expand(b, 1, -1)], 1)
            keys = self.keys_conv.unflatten(1, (g, g))[:, :rows, :cols].flatten(1, 2)
            out = keys.new_empty(b, len(MULTIMASK), UPSCALE * rows, UPSCALE * cols)
            logits = out.view(b * len(MULTIMASK), -1)                                # each mask's, row by row
            step = max(1, TOKEN_TILE // (b * cols))                                   # token rows a tile
            width1, width2 = values.shape[-1], self.up2_w.shape[-1]                   # 4*64, 4*32 channels
            buffer1 = keys.new_empty(b * step * cols * width1)                        # reused by every tile:
            buffer2 = keys.new_empty(b * step * cols * 4 * width2)                    # no fresh pages
            buffer3 = keys.new_empty(b * len(MULTIMASK) * step * cols * UPSCALE ** 2)
            order = _grid_order(step, cols, keys.device)                              # a shorter tile's: a prefix
            for i in range(0, rows, step):                                            # tiles stay in cache
                part = slice(i * cols, min(i + step, rows) * cols)
                n = part.stop - part.start
                up = buffer1[:b * n * width1].view(b, n, -1)
                up = torch.addcmul(self.conv_b2, keys[:, part], rstd12[:, part], out=up)
                up = up.baddbmm_(coeffs[:, :, part].transpose(1, 2), values)            # [B, tile, 4*64]
                up = _gelu_(F.layer_norm(up.view(b, n * 4, -1), (width1 // 4,), norm.weight, norm.bias, norm.eps))
                up = torch.matmul(up, self.up2_w, out=buffer2[:b * n * 4 * width2].view(b, n * 4, -1))
                up = _gelu_(up.add_(self.up2_b)).view(b, n * 16, -1)                    # [B, tile*4*4, 32]
                low = (hyper @ up.transpose(1, 2)).view(b * len(MULTIMASK), -1)       # [B*3, tile*16]
                tile = torch.index_select(low, 1, order[:low.shape[1]], out=buffer3[:low.numel()].view(low.shape))
                logits[:, i * cols * UPSCALE ** 2:part.stop * UPSCALE ** 2].copy_(tile)
        return out
