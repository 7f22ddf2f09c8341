"""qr-cl's CLIP and SAM against the reference packages (``open_clip``, ``segment_anything``) on the
same small random weights. Skipped where they cannot be imported: both import torchvision, which
does not load beside the pinned CPU torch on this project's machines."""
from __future__ import annotations

from functools import partial

import numpy as np
import pytest
import torch

from qr_cl.app.features.clip_model import load_clip
from qr_cl.app.features.sam_model import load_sam
from tests.app.features_helpers import assert_matches_predictor


def test_clip_matches_open_clip(tmp_path):
    open_clip = pytest.importorskip("open_clip")
    from open_clip.model import CLIPTextCfg, CLIPVisionCfg

    torch.manual_seed(0)
    ref = open_clip.model.CLIP(32, CLIPVisionCfg(layers=2, width=64, patch_size=16, image_size=64, head_width=64),
                               CLIPTextCfg(context_length=16, vocab_size=600, width=64, heads=1, layers=1)).eval()
    torch.save(ref.state_dict(), tmp_path / "open_clip_pytorch_model.bin")
    ours = load_clip(tmp_path / "open_clip_pytorch_model.bin")
    images, tokens = torch.rand(3, 3, 64, 64), torch.randint(1, 598, (2, 16))
    tokens[:, 10] = 599
    with torch.no_grad():
        torch.testing.assert_close(ours.encode_image(images), ref.encode_image(images), atol=1e-4, rtol=1e-4)
        torch.testing.assert_close(ours.encode_text(tokens), ref.encode_text(tokens), atol=1e-4, rtol=1e-4)


def test_sam_matches_segment_anything(tmp_path):
    pytest.importorskip("segment_anything")
    from segment_anything import SamPredictor
    from segment_anything.modeling import ImageEncoderViT, MaskDecoder, PromptEncoder, Sam, TwoWayTransformer

    torch.manual_seed(0)
    ref = Sam(ImageEncoderViT(depth=2, embed_dim=64, num_heads=2, global_attn_indexes=(1,), window_size=14,
                              use_rel_pos=True, out_chans=256, qkv_bias=True,
                              norm_layer=partial(torch.nn.LayerNorm, eps=1e-6)),
              PromptEncoder(embed_dim=256, image_embedding_size=(64, 64), input_image_size=(1024, 1024),
                            mask_in_chans=16),
              MaskDecoder(num_multimask_outputs=3, transformer=TwoWayTransformer(depth=2, embedding_dim=256,
                                                                                 mlp_dim=2048, num_heads=8),
                          transformer_dim=256, iou_head_depth=3, iou_head_hidden_dim=256)).eval()
    with torch.no_grad():
        for p in ref.image_encoder.parameters():
            p.add_(0.02 * torch.randn_like(p))
    torch.save(ref.state_dict(), tmp_path / "sam_vit_tiny.pth")
    ours = load_sam(tmp_path / "sam_vit_tiny.pth")
    image = (np.random.default_rng(0).random((48, 64, 3)) * 255).astype(np.uint8)
    points = np.array([[10.0, 20.0], [40.0, 8.0], [63.0, 47.0]])
    assert_matches_predictor(SamPredictor, ref, ours, image, points)
