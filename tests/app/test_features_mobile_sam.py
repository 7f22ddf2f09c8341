"""MobileSAM (a TinyViT image encoder before SAM's decoder) from a ``mobile_sam.pt`` of the official
names and shapes: the parameter table, loading and use, float64 twins of the TinyViT block and the
MBConv block, the official ``mobile_sam`` package where it imports (it needs timm and torchvision,
so it is skipped on this project's machines), and wrong files."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from qr_cl.app.features.errors import FeaturesError
from qr_cl.app.features.random_models import (SAM_ARCHITECTURES, random_clip, random_sam, randomise,
                                              save_weights)
from qr_cl.app.features.sam_model import Sam, SamArchitecture, load_sam, sam_architecture
from qr_cl.app.features.tiny_vit import MBConv, TinyViTBlock, TinyVitArchitecture
from tests.app.features_helpers import assert_matches_predictor, tiny_clip_arch

#: Names and shapes of the official ``mobile_sam.pt`` (mobile_sam/build_sam.py, build_sam_vit_t).
OFFICIAL_SHAPES = {
    "image_encoder.patch_embed.seq.0.c.weight": (32, 3, 3, 3),
    "image_encoder.patch_embed.seq.0.bn.num_batches_tracked": (),
    "image_encoder.patch_embed.seq.2.c.weight": (64, 32, 3, 3),
    "image_encoder.layers.0.blocks.0.conv1.c.weight": (256, 64, 1, 1),
    "image_encoder.layers.0.blocks.0.conv2.c.weight": (256, 1, 3, 3),
    "image_encoder.layers.0.blocks.1.conv3.bn.running_var": (64,),
    "image_encoder.layers.0.downsample.conv1.c.weight": (128, 64, 1, 1),
    "image_encoder.layers.0.downsample.conv2.c.weight": (128, 1, 3, 3),
    "image_encoder.layers.1.blocks.0.attn.norm.weight": (128,),
    "image_encoder.layers.1.blocks.0.attn.qkv.weight": (384, 128),
    "image_encoder.layers.1.blocks.0.attn.attention_biases": (4, 49),
    "image_encoder.layers.1.blocks.1.local_conv.c.weight": (128, 1, 3, 3),
    "image_encoder.layers.1.blocks.1.mlp.fc1.weight": (512, 128),
    "image_encoder.layers.1.downsample.conv3.c.weight": (160, 160, 1, 1),
    "image_encoder.layers.2.blocks.5.attn.attention_biases": (5, 196),
    "image_encoder.layers.2.blocks.5.mlp.fc2.weight": (160, 640),
    "image_encoder.layers.2.downsample.conv2.c.weight": (320, 1, 3, 3),
    "image_encoder.layers.3.blocks.1.attn.attention_biases": (10, 49),
    "image_encoder.layers.3.blocks.1.attn.proj.weight": (320, 320),
    "image_encoder.layers.3.blocks.1.mlp.norm.bias": (320,),
    "image_encoder.neck.0.weight": (256, 320, 1, 1),
    "image_encoder.neck.1.weight": (256,),
    "image_encoder.neck.2.weight": (256, 256, 3, 3),
    "image_encoder.neck.3.bias": (256,),
    "mask_decoder.iou_prediction_head.layers.2.weight": (4, 256),
}
#: Parameters of the official image encoder less its unused ImageNet classifier (6,065,532 in all,
#: of which ``norm_head`` and ``head`` [1000, 320] hold 321,640).
ENCODER_PARAMETERS = 5_743_892
#: The classifier the official file carries (and qr-cl ignores).
HEAD_SHAPES = {"image_encoder.norm_head.weight": (320,), "image_encoder.norm_head.bias": (320,),
               "image_encoder.head.weight": (1000, 320), "image_encoder.head.bias": (1000,)}
IMAGE = (np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8)
POINTS = np.array([[10.0, 20.0], [40.0, 8.0], [63.0, 47.0]])


@pytest.fixture(scope="module")
def mobile_sam_state() -> dict[str, torch.Tensor]:
    """A random MobileSAM's state dict with the official file's classifier head added."""
    state = random_sam(SAM_ARCHITECTURES["mobile_sam"], seed=3).state_dict()
    gen = torch.Generator().manual_seed(4)
    return {**state, **{k: torch.randn(shape, generator=gen) for k, shape in HEAD_SHAPES.items()}}


def test_official_names_shapes_and_use(mobile_sam_state, tmp_path):
    for name, shape in OFFICIAL_SHAPES.items():
        assert tuple(mobile_sam_state[name].shape) == shape, name
    assert not any(k.startswith("image_encoder.layers.3.downsample") for k in mobile_sam_state)
    sam = Sam(SAM_ARCHITECTURES["mobile_sam"])
    assert sum(p.numel() for p in sam.image_encoder.parameters()) == ENCODER_PARAMETERS
    assert not any(".head." in k or "norm_head" in k for k in sam.state_dict())
    torch.save(mobile_sam_state, tmp_path / "mobile_sam.pt")
    loaded = load_sam(tmp_path / "mobile_sam.pt")
    assert loaded.arch.name == "mobile_sam" and loaded.arch == SAM_ARCHITECTURES["mobile_sam"]
    assert all(torch.equal(v.float(), mobile_sam_state[k].float()) for k, v in loaded.state_dict().items())
    view = loaded.embed(IMAGE)
    assert view.embedding.shape == (1, 256, 64, 64) and torch.isfinite(view.embedding).all()
    logits, iou = view.predict(POINTS)
    assert logits.shape == (3, 3, 48, 64) and iou.shape == (3, 3) and torch.isfinite(logits).all()


def test_other_tiny_vit_stages_read_from_shapes(tmp_path):
    tiny_vit_11m = TinyVitArchitecture((64, 128, 256, 448), (2, 2, 6, 2), (0, 4, 8, 14), (0, 7, 14, 7))
    arch = SamArchitecture(tiny_vit=tiny_vit_11m)
    with torch.device("meta"):
        sam = Sam(arch)
    read = sam_architecture({k: torch.empty(v.shape, device="meta") for k, v in sam.state_dict().items()}, tmp_path)
    assert read == arch and read.name == "tiny_vit_w64-128-256-448"


def _conv_bn_twin(conv_bn, x):
    """A convolution, then BatchNorm with running statistics, written out."""
    c, bn = conv_bn.c, conv_bn.bn
    y = F.conv2d(x, c.weight, None, c.stride, c.padding, groups=c.groups)
    scale = (bn.weight / torch.sqrt(bn.running_var + bn.eps))[:, None, None]
    return (y - bn.running_mean[:, None, None]) * scale + bn.bias[:, None, None]


def _gelu(x):
    return 0.5 * x * (1 + torch.erf(x / math.sqrt(2)))


def test_mbconv_matches_twin():
    block = randomise(MBConv(6), seed=5).double().eval()
    x = torch.randn(2, 6, 9, 7, dtype=torch.float64)
    y = _gelu(_conv_bn_twin(block.conv2, _gelu(_conv_bn_twin(block.conv1, x))))
    torch.testing.assert_close(block(x), _gelu(x + _conv_bn_twin(block.conv3, y)))


def _offset_numbers(window: int) -> dict[tuple[int, int], int]:
    """The official numbering of (|dy|, |dx|) offsets: in the order met over all token pairs."""
    points = [(i, j) for i in range(window) for j in range(window)]
    numbers: dict[tuple[int, int], int] = {}
    for p in points:
        for q in points:
            numbers.setdefault((abs(p[0] - q[0]), abs(p[1] - q[1])), len(numbers))
    return numbers


def _layer_norm(x, norm):
    mean = x.mean(-1, keepdim=True)
    var = ((x - mean) ** 2).mean(-1, keepdim=True)
    return (x - mean) / torch.sqrt(var + norm.eps) * norm.weight + norm.bias


def _tiny_vit_block_twin(block, x):
    """[C, H, W] through a TinyViT block, window by window and head by head."""
    c, h, w = x.shape
    n, attn = block.window, block.attn
    d = c // attn.heads
    numbers = _offset_numbers(n)
    cells = [(i, j) for i in range(n) for j in range(n)]
    grid = torch.zeros(math.ceil(h / n) * n, math.ceil(w / n) * n, c, dtype=x.dtype)
    grid[:h, :w] = x.permute(1, 2, 0)
    out = torch.zeros_like(grid)
    for wy in range(0, grid.shape[0], n):
        for wx in range(0, grid.shape[1], n):
            tokens = _layer_norm(grid[wy:wy + n, wx:wx + n].reshape(n * n, c), attn.norm)
            qkv = tokens @ attn.qkv.weight.T + attn.qkv.bias
            heads = []
            for head in range(attn.heads):
                q, k, v = qkv[:, 3 * d * head:3 * d * (head + 1)].split(d, 1)
                logits = q @ k.T / math.sqrt(d)
                for a, p in enumerate(cells):
                    for b, r in enumerate(cells):
                        logits[a, b] += attn.attention_biases[head, numbers[abs(p[0] - r[0]), abs(p[1] - r[1])]]
                heads.append(torch.softmax(logits, -1) @ v)
            out[wy:wy + n, wx:wx + n] = (torch.cat(heads, 1) @ attn.proj.weight.T + attn.proj.bias).view(n, n, c)
    x = x + out[:h, :w].permute(2, 0, 1)
    x = _conv_bn_twin(block.local_conv, x[None])[0].permute(1, 2, 0)
    mlp = block.mlp
    hidden = _gelu(_layer_norm(x, mlp.norm) @ mlp.fc1.weight.T + mlp.fc1.bias)
    return (x + hidden @ mlp.fc2.weight.T + mlp.fc2.bias).permute(2, 0, 1)


@pytest.mark.parametrize("size", [(3, 3), (5, 7)])
def test_tiny_vit_block_matches_twin(size):
    block = randomise(TinyViTBlock(8, 2, 3), seed=6).double().eval()
    with torch.no_grad():
        block.attn.norm.bias.normal_()                     # the padding's keys are the norm's bias
        block.attn.attention_biases.mul_(5)
    x = torch.randn(1, 8, *size, dtype=torch.float64)
    torch.testing.assert_close(block(x)[0], _tiny_vit_block_twin(block, x[0]))


def test_matches_official_mobile_sam(mobile_sam_state, tmp_path):
    pytest.importorskip("mobile_sam")
    from mobile_sam import SamPredictor, sam_model_registry

    state = {**random_sam(SAM_ARCHITECTURES["mobile_sam"], seed=7, confident=False).state_dict(),
             **{k: v for k, v in mobile_sam_state.items() if k in HEAD_SHAPES}}
    ref = sam_model_registry["vit_t"]()
    ref.load_state_dict(state)
    ref.eval()
    torch.save(state, tmp_path / "mobile_sam.pt")
    ours = load_sam(tmp_path / "mobile_sam.pt")
    assert_matches_predictor(SamPredictor, ref, ours, IMAGE, POINTS)


def _fails(path, match: str) -> str:
    with pytest.raises(FeaturesError, match=match) as err:
        load_sam(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message
    return message


def test_wrong_files_fail_in_one_line(mobile_sam_state, tmp_path):
    (tmp_path / "clip").mkdir()
    clip = save_weights(random_clip(tiny_clip_arch(600), seed=1), tmp_path / "clip" / "mobile_sam.pt")
    _fails(clip, "a CLIP checkpoint")
    path = tmp_path / "mobile_sam.pt"
    torch.save({k: v for k, v in mobile_sam_state.items() if ".neck." not in k}, path)
    assert "image_encoder.neck.0.weight" in _fails(path, "a SAM mobile_sam lacks 6 weights")
    torch.save({k: v for k, v in mobile_sam_state.items() if ".layers.3." not in k}, path)
    _fails(path, r"stages \[0, 1, 2\], not 0-3")
    torch.save({k: v for k, v in mobile_sam_state.items() if ".layers.2.blocks.0.attn." not in k}, path)
    _fails(path, "without image_encoder.layers.2.blocks.0.attn.attention_biases")
    wrong = dict(mobile_sam_state)
    wrong["image_encoder.layers.1.blocks.1.mlp.fc1.weight"] = torch.zeros(256, 128)
    torch.save(wrong, path)
    _fails(path, "do not fit a SAM mobile_sam")
    torch.save(mobile_sam_state, path)
    path.write_bytes(path.read_bytes()[:1 << 20])                  # a download cut short
    _fails(path, "not a readable weights file")
