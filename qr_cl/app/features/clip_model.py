"""CLIP's ViT image and text towers (OpenAI CLIP and OpenCLIP ``ViT-*`` models) in plain torch,
with the parameter names of both publishers' weights files so their state dicts load as they are.

Image tower: a PxP patch convolution, a class token and learned positions, ``ln_pre``, pre-norm
residual blocks (multi-head attention, a 2-layer MLP), ``ln_post`` on the class token and a
projection to the embedding. Text tower: token and position embeddings, the same blocks under a
causal mask, ``ln_final`` and a projection of the end-of-text token (the largest token id).

The architecture is read from the weight shapes (:func:`clip_architecture`); the one thing the
shapes cannot tell, the MLP's activation (QuickGELU in OpenAI's models, GELU in OpenCLIP's own),
comes from the file where it says so (an OpenAI TorchScript archive, or an
``open_clip_config.json`` beside the weights) or from the ``-quickgelu`` suffix of the model name.
"""
from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from .errors import FeaturesError
from .weights import load_state_dict, missing_keys

#: OpenCLIP's size letters of the image towers by width, and their attention head widths.
SIZE_BY_WIDTH = {768: "B", 1024: "L", 1280: "H", 1408: "g", 1664: "bigG"}
HEAD_WIDTH = {768: 64, 1024: 64, 1280: 80, 1408: 88, 1664: 104}
#: Text towers' attention head width.
TEXT_HEAD_WIDTH = 64
#: CLIP's image normalisation (OpenAI's mean and standard deviation per RGB channel, in [0, 1]).
IMAGE_MEAN = (0.48145466, 0.4578275, 0.40821073)
IMAGE_STD = (0.26862954, 0.26130258, 0.27577711)
#: The model LangSplat encodes its masks with.
DEFAULT_MODEL = "ViT-B-16"
_NAME = re.compile(r"^ViT-(B|L|H|g|bigG)-(\d+)(?:-(\d+))?(-quickgelu)?$")


@dataclass(frozen=True)
class ClipArchitecture:
    """A CLIP ViT's shape: image tower ``width``, ``layers``, ``patch`` px, ``image_size`` px,
    ``mlp_width``; text tower ``text_width``, ``text_layers``, ``context`` tokens, ``vocab``
    tokens, ``text_mlp_width`` (0 when the file has no text tower); ``embed_dim`` of the joint
    space and ``quick_gelu`` activation."""

    width: int
    layers: int
    patch: int
    image_size: int
    mlp_width: int
    embed_dim: int
    text_width: int
    text_layers: int
    context: int
    vocab: int
    text_mlp_width: int
    quick_gelu: bool

    @property
    def name(self) -> str:
        """The OpenCLIP model name, e.g. ``ViT-B-16`` or ``ViT-L-14-336-quickgelu``."""
        size = SIZE_BY_WIDTH.get(self.width, f"w{self.width}")
        res = "" if self.image_size == 224 else f"-{self.image_size}"
        return f"ViT-{size}-{self.patch}{res}" + ("-quickgelu" if self.quick_gelu else "")

    @property
    def heads(self) -> int:
        return self.width // HEAD_WIDTH.get(self.width, 64)


def _count_blocks(state: dict[str, torch.Tensor], prefix: str) -> int:
    pattern = re.compile(re.escape(prefix) + r"(\d+)\.")
    return len({int(m.group(1)) for k in state if (m := pattern.match(k))})


def _file_says_quick_gelu(path: Path, torchscript: bool) -> bool | None:
    """True for OpenAI's TorchScript archives; an ``open_clip_config.json`` beside the weights
    says it in ``model_cfg.quick_gelu``; None when the file says nothing."""
    if torchscript:
        return True
    config = path.parent / "open_clip_config.json"
    if config.is_file():
        try:
            return bool(json.loads(config.read_text())["model_cfg"].get("quick_gelu", False))
        except (json.JSONDecodeError, KeyError, TypeError, AttributeError):
            raise FeaturesError(f"{config}: not an OpenCLIP config (expected a 'model_cfg' object)") from None
    return None


def clip_architecture(state: dict[str, torch.Tensor], path: Path, quick_gelu: bool) -> ClipArchitecture:
    """The architecture of a CLIP ViT state dict (module docstring); FeaturesError naming
    ``path`` when it is not one."""
    need = ["visual.conv1.weight", "visual.positional_embedding", "visual.proj", "visual.class_embedding"]
    absent = [k for k in need if k not in state]
    if absent:
        kind = "a SAM checkpoint" if any(k.startswith("image_encoder.") for k in state) else "not a CLIP ViT"
        raise FeaturesError(f"{path}: {kind}: lacks {', '.join(absent)} (--clip-weights)")
    conv = state["visual.conv1.weight"]
    width, patch = conv.shape[0], conv.shape[-1]
    grid = math.isqrt(state["visual.positional_embedding"].shape[0] - 1)
    text = "token_embedding.weight" in state
    return ClipArchitecture(
        width=width, layers=_count_blocks(state, "visual.transformer.resblocks."), patch=patch,
        image_size=grid * patch, mlp_width=state["visual.transformer.resblocks.0.mlp.c_fc.weight"].shape[0],
        embed_dim=state["visual.proj"].shape[1],
        text_width=state["ln_final.weight"].shape[0] if text else 0,
        text_layers=_count_blocks(state, "transformer.resblocks.") if text else 0,
        context=state["positional_embedding"].shape[0] if text else 0,
        vocab=state["token_embedding.weight"].shape[0] if text else 0,
        text_mlp_width=state["transformer.resblocks.0.mlp.c_fc.weight"].shape[0] if text else 0,
        quick_gelu=quick_gelu)


class QuickGELU(nn.Module):
    """x * sigmoid(1.702 x), OpenAI CLIP's activation."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * torch.sigmoid(1.702 * x)


class Attention(nn.Module):
    """Multi-head self-attention with one packed input projection (``in_proj_weight`` [3W, W])."""

    def __init__(self, width: int, heads: int):
        super().__init__()
        self.heads = heads
        self.in_proj_weight = nn.Parameter(torch.empty(3 * width, width))
        self.in_proj_bias = nn.Parameter(torch.empty(3 * width))
        self.out_proj = nn.Linear(width, width)

    def forward(self, x: torch.Tensor, causal: bool = False) -> torch.Tensor:
        b, n, w = x.shape
        q, k, v = F.linear(x, self.in_proj_weight, self.in_proj_bias).view(b, n, 3, self.heads, -1).permute(2, 0, 3, 1, 4)
        y = F.scaled_dot_product_attention(q, k, v, is_causal=causal)
        return self.out_proj(y.transpose(1, 2).reshape(b, n, w))


class Mlp(nn.Module):
    """``c_fc`` -> activation -> ``c_proj``."""

    def __init__(self, width: int, hidden: int, quick_gelu: bool):
        super().__init__()
        self.c_fc, self.c_proj = nn.Linear(width, hidden), nn.Linear(hidden, width)
        self.act = QuickGELU() if quick_gelu else nn.GELU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.c_proj(self.act(self.c_fc(x)))


class ResidualBlock(nn.Module):
    """x + attn(ln_1(x)), then + mlp(ln_2(x))."""

    def __init__(self, width: int, heads: int, hidden: int, quick_gelu: bool):
        super().__init__()
        self.ln_1, self.ln_2 = nn.LayerNorm(width), nn.LayerNorm(width)
        self.attn = Attention(width, heads)
        self.mlp = Mlp(width, hidden, quick_gelu)

    def forward(self, x: torch.Tensor, causal: bool = False) -> torch.Tensor:
        x = x + self.attn(self.ln_1(x), causal)
        return x + self.mlp(self.ln_2(x))


class Transformer(nn.Module):
    """``resblocks``: a stack of :class:`ResidualBlock`."""

    def __init__(self, width: int, layers: int, heads: int, hidden: int, quick_gelu: bool):
        super().__init__()
        self.resblocks = nn.ModuleList(ResidualBlock(width, heads, hidden, quick_gelu) for _ in range(layers))

    def forward(self, x: torch.Tensor, causal: bool = False) -> torch.Tensor:
        for block in self.resblocks:
            x = block(x, causal)
        return x


class VisionTower(nn.Module):
    """CLIP's ViT image encoder (names as ``visual.*`` in the weights files)."""

    def __init__(self, arch: ClipArchitecture):
        super().__init__()
        grid = arch.image_size // arch.patch
        self.conv1 = nn.Conv2d(3, arch.width, arch.patch, arch.patch, bias=False)
        self.class_embedding = nn.Parameter(torch.empty(arch.width))
        self.positional_embedding = nn.Parameter(torch.empty(grid * grid + 1, arch.width))
        self.ln_pre, self.ln_post = nn.LayerNorm(arch.width), nn.LayerNorm(arch.width)
        self.transformer = Transformer(arch.width, arch.layers, arch.heads, arch.mlp_width, arch.quick_gelu)
        self.proj = nn.Parameter(torch.empty(arch.width, arch.embed_dim))

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = self.conv1(images).flatten(2).transpose(1, 2)
        cls = self.class_embedding.to(x.dtype).expand(x.shape[0], 1, -1)
        x = self.ln_pre(torch.cat([cls, x], 1) + self.positional_embedding.to(x.dtype))
        return self.ln_post(self.transformer(x)[:, 0]) @ self.proj


class Clip(nn.Module):
    """A CLIP ViT: ``visual`` (:class:`VisionTower`) and, when ``arch`` has one, the text tower
    (``token_embedding``, ``positional_embedding``, ``transformer``, ``ln_final``,
    ``text_projection``) under the weights files' names."""

    def __init__(self, arch: ClipArchitecture):
        super().__init__()
        self.arch = arch
        self.visual = VisionTower(arch)
        if arch.text_width:
            self.token_embedding = nn.Embedding(arch.vocab, arch.text_width)
            self.positional_embedding = nn.Parameter(torch.empty(arch.context, arch.text_width))
            self.transformer = Transformer(arch.text_width, arch.text_layers, arch.text_width // TEXT_HEAD_WIDTH,
                                           arch.text_mlp_width, arch.quick_gelu)
            self.ln_final = nn.LayerNorm(arch.text_width)
            self.text_projection = nn.Parameter(torch.empty(arch.text_width, arch.embed_dim))
            self.logit_scale = nn.Parameter(torch.tensor(math.log(1 / 0.07)))

    def encode_image(self, images: torch.Tensor) -> torch.Tensor:
        """[B, E] embeddings (not normalised) of ``images`` [B, 3, S, S] normalised by
        :data:`IMAGE_MEAN`/:data:`IMAGE_STD`, S = ``arch.image_size``."""
        return self.visual(images)

    def encode_text(self, tokens: torch.Tensor) -> torch.Tensor:
        """[B, E] embeddings (not normalised) of ``tokens`` [B, context] int64 (start, BPE ids,
        end-of-text, zero padding)."""
        x = self.token_embedding(tokens) + self.positional_embedding
        x = self.ln_final(self.transformer(x, causal=True))
        return x[torch.arange(len(tokens), device=tokens.device), tokens.argmax(-1)] @ self.text_projection


def parse_model_name(name: str) -> tuple[str, int, int, bool]:
    """(size letter, patch px, image px, quick_gelu) of an OpenCLIP ViT name such as
    ``ViT-B-16``, ``ViT-L-14-336`` or ``ViT-B-32-quickgelu``; FeaturesError for another name."""
    m = _NAME.match(name)
    if not m:
        raise FeaturesError(f"--clip-model {name!r}: not an OpenCLIP ViT name such as ViT-B-16, ViT-L-14-336 "
                            "or ViT-B-32-quickgelu")
    return m.group(1), int(m.group(2)), int(m.group(3) or 224), bool(m.group(4))


def load_clip(path: str | os.PathLike, model: str | None = None) -> Clip:
    """The CLIP model in the weights file ``path`` (CPU, float32, eval mode). ``model`` (an
    OpenCLIP name, e.g. ``ViT-B-16``) is checked against the file and sets the activation where
    the file does not say it; FeaturesError naming the file for a missing, unreadable or
    mismatched one."""
    path = Path(path)
    state, torchscript = load_state_dict(path, "--clip-weights")
    said = _file_says_quick_gelu(path, torchscript)
    named = parse_model_name(model) if model else None
    if said is not None and named is not None and named[3] != said:
        raise FeaturesError(f"{path}: --clip-model {model} {'asks for' if named[3] else 'rules out'} QuickGELU, "
                            f"but the file's model {'uses' if said else 'does not use'} it")
    arch = clip_architecture(state, path, said if said is not None else bool(named and named[3]))
    if named is not None:
        size, patch, image, _ = named
        found = (SIZE_BY_WIDTH.get(arch.width), arch.patch, arch.image_size)
        if found != (size, patch, image):
            raise FeaturesError(f"{path}: holds a {arch.name} (image tower width {arch.width}, patch {arch.patch}, "
                                f"{arch.image_size} px), not the {model} named by --clip-model")
    net = Clip(arch)
    state = {k: v for k, v in state.items() if k in net.state_dict()}
    absent = missing_keys(state, net)
    if absent:
        raise FeaturesError(f"{path}: a {arch.name} lacks {len(absent)} weights, e.g. {absent[0]} (--clip-weights)")
    try:
        net.load_state_dict({k: v.float() for k, v in state.items()})
    except RuntimeError as exc:
        raise FeaturesError(f"{path}: weights do not fit a {arch.name}: {str(exc).splitlines()[-1].strip()}") from None
    return net.eval()
