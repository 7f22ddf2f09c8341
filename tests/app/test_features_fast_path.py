"""The rearranged decoder, the taps upsampling, the stability bound and the CLIP deduplication of
``qr-cl features`` against today's path (tests/app/features_twin.py) and against float64 twins."""
from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from qr_cl.app.features import frames
from qr_cl.app.features.frames import encode_crops, frame_features
from qr_cl.app.features.mask_upsampling import Taps, stability_bound, stability_scores, upsample
from qr_cl.app.features.masks import MaskSettings
from qr_cl.app.features.point_decoder import PointDecoder
from qr_cl.app.features.random_models import random_clip, random_sam
from qr_cl.app.features.sam_model import upsampling_matrix
from tests.app.features_helpers import TINY_SAM, tiny_clip_arch
from tests.app.features_twin import reference_frame, reference_predict


def _decoder_inputs(sam, prompts: int, seed: int):
    gen = torch.Generator().manual_seed(seed)
    image = torch.randn(1, 256, 64, 64, generator=gen)
    pe = sam.prompt_encoder.pe_layer.grid(64)[None]
    dense = sam.prompt_encoder.no_mask_embed.weight.view(1, -1, 1, 1)
    sparse = sam.prompt_encoder.embed_points(torch.rand(prompts, 1, 2, generator=gen) * 1024, torch.ones(prompts, 1))
    return image, pe, dense, sparse


def _with_random_norms_and_biases(sam, seed: int):
    """``sam`` with its decoder's LayerNorm gains and biases and its linear biases random (the
    random models have gains 1 and biases 0, which would hide their terms in the decoder's maths)."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for module in sam.mask_decoder.modules():
            if isinstance(module, torch.nn.LayerNorm):
                module.weight.copy_(0.5 + torch.rand(module.weight.shape, generator=gen))
            if isinstance(module, (torch.nn.LayerNorm, torch.nn.Linear)) and module.bias is not None:
                module.bias.copy_(0.3 * torch.randn(module.bias.shape, generator=gen))
    return sam


@pytest.mark.parametrize("seed", [0, 1])
def test_point_decoder_is_the_published_decoder(seed):
    sam = _with_random_norms_and_biases(random_sam(TINY_SAM, seed=seed, confident=False), seed)
    image, pe, dense, sparse = _decoder_inputs(sam, 5, seed)
    with torch.no_grad():
        twin = copy.deepcopy(sam.mask_decoder).double()                     # the float64 twin
        ref = twin(image.double(), pe.double(), sparse.double(), dense.double())
        fast = PointDecoder(sam.mask_decoder, image, pe, dense)
        tokens = fast.transform(sparse)
        torch.testing.assert_close(fast.iou(tokens).double(), ref[1][:, 1:], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(fast.masks(tokens).double(), ref[0][:, 1:], atol=1e-4, rtol=1e-4)
        window = fast.masks(tokens.take(torch.tensor([3, 0])), 48, 37)       # a window, prompts picked
        torch.testing.assert_close(window.double(), ref[0][[3, 0], 1:, :192, :148], atol=1e-4, rtol=1e-4)


@pytest.mark.parametrize("out,crop", [(480, 768), (322, 820), (47, 1024), (1300, 1024)])
def test_taps_are_the_dense_resize(out, crop):
    matrix = upsampling_matrix(out, crop, 256)
    taps = Taps.of(matrix)
    assert taps.span <= 3
    assert taps.reads == int((matrix != 0).any(0).nonzero().max()) + 1
    low = torch.randn(2, 256, 256, dtype=torch.float64)
    dense = upsampling_matrix(out, crop, 256).double()
    got = upsample(low[:, :taps.reads], Taps.of(dense), Taps.of(dense))
    torch.testing.assert_close(got, dense @ low @ dense.T)
    assert int(taps.windows.sum()) == out


def test_stability_bound_never_drops_a_passing_mask():
    gen = torch.Generator().manual_seed(0)
    rows, cols = Taps.of(upsampling_matrix(120, 768, 256)), Taps.of(upsampling_matrix(160, 1024, 256))
    yy, xx = torch.meshgrid(torch.arange(256.0), torch.arange(256.0), indexing="ij")
    centre = torch.rand(64, 2, 1, 1, generator=gen) * 256
    radius = torch.rand(64, 1, 1, generator=gen) * 80 + 5
    slope = torch.logspace(-2, 1, 64)[:, None, None]                      # blurred to sharp blobs
    low = slope * (radius - ((yy - centre[:, 0]) ** 2 + (xx - centre[:, 1]) ** 2).sqrt())
    low[:8] += torch.randn(8, 256, 256, generator=gen) * 3               # and noisy ones
    low[8] = 5.0                                                          # all above: both counts full
    low[9] = 0.5                                                          # none above +1
    low[10] = -5.0                                                        # none above -1: 0/0
    exact = stability_scores(upsample(low, rows, cols), 1.0)
    bound = stability_bound(low, rows, cols, 1.0)
    known = ~torch.isnan(exact)
    assert (bound[known] >= exact[known]).all()
    assert bound[9] == 0 and bound[8] == 1 and bound[10] == 1
    assert ((bound < 0.85) & known).sum() > 10                            # it does drop masks
    assert (bound - exact)[11:][known[11:]].abs().median() < 0.1          # near the score of smooth masks


def _sam_with(iou_bias: float, sharpen: float, seed: int = 2):
    """The tiny SAM with its IoU head's bias and mask sharpness set (masks that pass and fail)."""
    sam = random_sam(TINY_SAM, seed=seed, confident=True)
    with torch.no_grad():
        sam.mask_decoder.iou_prediction_head.layers[-1].bias.fill_(iou_bias)
        for mlp in sam.mask_decoder.output_hypernetworks_mlps:
            mlp.layers[-1].weight.mul_(sharpen / 1000.0)
    return sam


def _drawn_image(height: int = 60, width: int = 80) -> np.ndarray:
    yy, xx = np.mgrid[:height, :width]
    img = np.stack([xx * 3 % 256, yy * 4 % 256, (xx * yy) % 256], -1).astype(np.uint8)
    img[(xx - 25) ** 2 + (yy - 30) ** 2 < 200] = (230, 40, 40)
    img[8:22, 50:75] = (20, 200, 60)
    return img


@pytest.mark.parametrize("seed,iou_bias,sharpen,nms,masks,batch", [(2, 1.0, 1000.0, 0.95, 8, 64), (3, 0.7, 20.0, 0.7, 3, 64),
                                                                  (2, 1.0, 1000.0, 0.95, 8, 7)])
def test_frame_features_equal_todays_path(seed, iou_bias, sharpen, nms, masks, batch, monkeypatch):
    """LangSplat's whole frame (crops, levels, filters, CLIP) by the fast path and today's path,
    the 36 prompts of a crop in one batch or in six (masks kept from several batches); the fast
    path encodes each distinct mask once."""
    sam, clip = _sam_with(iou_bias, sharpen, seed), random_clip(tiny_clip_arch(600), seed=1)
    image = _drawn_image()
    settings = MaskSettings(points_per_side=6, points_per_batch=batch, crop_layers=1, min_area=20, box_nms=nms,
                            crop_nms=nms)
    ref = reference_frame(sam, clip, image, settings)
    encoded = []
    monkeypatch.setattr(frames, "encode_crops", lambda c, crops, b: encoded.append(len(crops)) or encode_crops(c, crops, b))
    got = frame_features(sam, clip, image, settings)
    assert sum(ref.counts) == masks                                          # the random SAM's masks
    assert got.counts == ref.counts
    assert sum(encoded) == len(np.unique(got.features, axis=0)) < sum(got.counts)
    for level in range(4):
        assert (got.ids[level] == ref.ids[level]).mean() >= 0.999
    cosine = (got.features * ref.features).sum(1) / np.linalg.norm(got.features, axis=1) / np.linalg.norm(ref.features, axis=1)
    assert cosine.min() >= 1 - 1e-5


def test_predict_is_todays_predict():
    sam = _sam_with(0.7, 20.0)
    view = sam.embed(_drawn_image(50, 90))
    points = np.array([[10.0, 20.0], [80.0, 5.0], [45.0, 49.0]])
    logits, iou = view.predict(points)
    ref_logits, ref_iou = reference_predict(view, points)
    torch.testing.assert_close(iou, ref_iou, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(logits, ref_logits, atol=1e-3, rtol=1e-4)
