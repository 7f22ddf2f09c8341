"""The parts of ``qr-cl features`` against readable float64 twins: SAM's mask upsampling, box
NMS, mask boxes, small regions, LangSplat's overlap filter, crops; architectures read from weight
shapes; the weights formats; the BPE tokenizer; the query's encoder check."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from qr_cl.app.features.boxes import box_iou, mask_boxes, nms
from qr_cl.app.features.clip_model import Clip, clip_architecture, load_clip
from qr_cl.app.features.errors import FeaturesError
from qr_cl.app.features.langsplat import id_map, mask_crops, overlap_filter
from qr_cl.app.features.masks import Masks, crop_boxes, point_grid, remove_small_regions
from qr_cl.app.features.random_models import (CLIP_ARCHITECTURES, SAM_ARCHITECTURES, random_clip, save_weights,
                                              write_vocabulary)
from qr_cl.app.features.sam_model import Sam, sam_architecture, upsampling_matrix
from qr_cl.app.features.tokenizer import ClipTokenizer
from qr_cl.app.features.weights import load_state_dict, read_safetensors, write_safetensors
from qr_cl.app.query.command import check_text_encoder
from qr_cl.app.query.text import QueryError
from tests.app.features_helpers import tiny_clip_arch


def test_upsampling_matrix_is_sams_two_resizes():
    low = torch.randn(2, 3, 16, 16, dtype=torch.float64)
    ref = F.interpolate(low, (64, 64), mode="bilinear", align_corners=False)[..., :40, :64]
    ref = F.interpolate(ref, (30, 47), mode="bilinear", align_corners=False)
    # the factor matrices of a 1024 input are exact for any low size; here a 64 input by scaling:
    ay = F.interpolate(F.interpolate(torch.eye(16, dtype=torch.float64)[None], 64, mode="linear")[..., :40], 30,
                       mode="linear")[0].T
    ax = F.interpolate(F.interpolate(torch.eye(16, dtype=torch.float64)[None], 64, mode="linear")[..., :64], 47,
                       mode="linear")[0].T
    torch.testing.assert_close(ay @ low @ ax.T, ref)
    m = upsampling_matrix(480, 768, 256)
    assert m.shape == (480, 256)
    torch.testing.assert_close(m.sum(1), torch.ones(480))       # interpolation weights sum to one


def _nms_twin(boxes, scores, thr):
    order = sorted(range(len(scores)), key=lambda i: (-scores[i], i))
    keep = []
    for i in order:
        ok = True
        for j in keep:
            lo = np.maximum(boxes[i, :2], boxes[j, :2])
            hi = np.minimum(boxes[i, 2:], boxes[j, 2:])
            inter = np.prod(np.clip(hi - lo, 0, None))
            area = lambda b: (b[2] - b[0]) * (b[3] - b[1])
            if inter / (area(boxes[i]) + area(boxes[j]) - inter) > thr:
                ok = False
        if ok:
            keep.append(i)
    return keep


def test_nms_and_boxes_match_twins():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 50, (40, 2))
    boxes = np.concatenate([xy, xy + rng.uniform(1, 30, (40, 2))], 1)
    scores = rng.choice([0.2, 0.5, 0.9], 40)                          # ties: index order
    for thr in (0.3, 0.7):
        got = nms(torch.tensor(boxes, dtype=torch.float32), torch.tensor(scores, dtype=torch.float32), thr)
        assert got.tolist() == _nms_twin(boxes, scores, thr)
    masks = torch.zeros(3, 10, 12, dtype=torch.bool)
    masks[0, 2:5, 3:9] = True
    masks[1, 7, 11] = True
    assert mask_boxes(masks).tolist() == [[3, 2, 8, 4], [11, 7, 11, 7], [0, 0, 0, 0]]
    assert torch.isnan(box_iou(torch.zeros(1, 4), torch.zeros(1, 4))).all()


def test_small_regions_holes_islands():
    mask = np.zeros((20, 20), bool)
    mask[2:12, 2:12] = True
    mask[5, 5] = False                               # a 1-px hole
    mask[16:18, 16:18] = True                        # a 4-px island
    filled, changed = remove_small_regions(mask, 10, holes=True)
    assert changed and filled[5, 5] and filled[16, 16]
    cleaned, changed = remove_small_regions(filled, 10, holes=False)
    assert changed and not cleaned[16:18, 16:18].any() and cleaned[2:12, 2:12].all()
    only_small = np.zeros((20, 20), bool)
    only_small[0, 0] = only_small[10, 10:13] = True
    kept, _ = remove_small_regions(only_small, 10, holes=False)
    assert kept.sum() == 3 and kept[10, 11]          # all small: the largest stays
    solid = np.ones((6, 6), bool)
    same, changed = remove_small_regions(solid, 10, holes=True)
    assert not changed and same is solid


def test_grid_and_crops():
    g = point_grid(4)
    assert g.shape == (16, 2) and g[0].tolist() == [0.125, 0.125] and g[1].tolist() == [0.375, 0.125]
    boxes = crop_boxes(480, 640, 1, 512 / 1500)
    assert boxes[0] == (0, 0, 640, 480) and len(boxes) == 5
    lap = int(512 / 1500 * 480)
    assert boxes[1] == (0, 0, math.ceil((lap + 640) / 2), math.ceil((lap + 480) / 2))
    assert boxes[2][0] == 0 and boxes[3][1] == 0                      # column by column
    assert max(b[2] for b in boxes[1:]) == 640 and max(b[3] for b in boxes[1:]) == 480


def _overlap_twin(masks, scores, iou_thr=0.8, score_thr=0.7, inner_thr=0.5):
    """LangSplat's mask NMS, pair by pair in float64."""
    n = len(masks)
    idx = sorted(range(n), key=lambda i: (-scores[i], i))
    m = [masks[i].astype(np.float64) for i in idx]
    s = [scores[i] for i in idx]
    area = [x.sum() for x in m]
    iou, inner = np.zeros((n, n)), np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            inter = (m[i] * m[j]).sum()
            iou[i, j] = inter / ((m[i] + m[j]) > 0).sum()
            val = 1 - (inter / area[j]) * (inter / area[i])
            if inter / area[i] < 0.5 and inter / area[j] >= 0.85:
                inner[i, j] = val
            if inter / area[i] >= 0.85 and inter / area[j] < 0.5:
                inner[j, i] = val
    top3 = set(sorted(range(n), key=lambda i: -s[i])[:3])
    keep = []
    for j in range(n):
        rules = [np.array([s[k] > score_thr for k in range(n)]),
                 np.array([max([inner[i, k] for i in range(k)] or [0]) <= 1 - inner_thr for k in range(n)]),
                 np.array([max([inner[i, k] for i in range(max(k - 1, 0), n)]) <= 1 - inner_thr
                           for k in range(n)])]
        ok = max([iou[i, j] for i in range(j)] or [0]) <= iou_thr
        for r in rules:
            ok = ok and (r[j] if r.any() else j in top3)
        if ok:
            keep.append(idx[j])
    return sorted(keep)


@pytest.mark.parametrize("seed", range(4))
def test_overlap_filter_matches_langsplat_twin(seed):
    rng = np.random.default_rng(seed)
    h, w, n = 24, 30, 9
    masks = np.zeros((n, h, w), bool)
    for k in range(n):
        y, x = rng.integers(0, h - 4), rng.integers(0, w - 4)
        masks[k, y:y + rng.integers(3, h - y + 1), x:x + rng.integers(3, w - x + 1)] = True
    masks[3] = masks[2]                              # a duplicate
    masks[5] = masks[4] | masks[6]                   # nesting
    stab = rng.uniform(0.85, 1.0, n)
    iou = rng.uniform(0.6 if seed % 2 else 0.75, 1.0, n)
    level = Masks(torch.tensor(masks), mask_boxes(torch.tensor(masks)), torch.tensor(iou, dtype=torch.float32),
                  torch.tensor(stab, dtype=torch.float32), torch.arange(n, dtype=torch.float32))   # tags
    got = overlap_filter(level)
    want = _overlap_twin(masks, (stab.astype(np.float32) * iou.astype(np.float32)).tolist())
    assert got.crop_areas.int().tolist() == want


def test_id_map_and_crops():
    masks = torch.zeros(2, 6, 8, dtype=torch.bool)
    masks[0, 1:5, 1:7] = True
    masks[1, 2:4, 2:4] = True
    level = Masks(masks, mask_boxes(masks), torch.ones(2), torch.ones(2), torch.ones(2))
    ids = id_map(level)
    assert ids[0, 0] == -1 and ids[1, 1] == 0 and ids[2, 2] == 1       # later masks win
    image = torch.full((6, 8, 3), 200, dtype=torch.uint8)
    crops = mask_crops(image, level, 12)
    assert crops.shape == (2, 3, 12, 12)
    # mask 0: box x 1..6, y 1..4 -> LangSplat cuts 5x3 px, centred in a 5x5 black square
    square = torch.zeros(1, 3, 5, 5)
    square[..., 1:4, :] = 200
    want = F.interpolate(square, size=(12, 12), mode="bilinear", align_corners=False).round() / 255
    torch.testing.assert_close(crops[:1], want)


def _shapes(module):
    return {k: torch.empty(v.shape, device="meta") for k, v in module.state_dict().items()}


@pytest.mark.parametrize("name", sorted(SAM_ARCHITECTURES))
def test_sam_variant_read_from_shapes(name, tmp_path):
    with torch.device("meta"):
        sam = Sam(SAM_ARCHITECTURES[name])
    assert sam_architecture(_shapes(sam), tmp_path) == SAM_ARCHITECTURES[name]
    assert sam_architecture(_shapes(sam), tmp_path).name == name


@pytest.mark.parametrize("name", sorted(CLIP_ARCHITECTURES))
def test_clip_architecture_read_from_shapes(name, tmp_path):
    with torch.device("meta"):
        clip = Clip(CLIP_ARCHITECTURES[name])
    arch = clip_architecture(_shapes(clip), tmp_path, False)
    assert arch == CLIP_ARCHITECTURES[name] and arch.name == name


def test_weights_formats_load_the_same_model(tmp_path):
    net = random_clip(tiny_clip_arch(600), seed=3)
    x = torch.rand(2, 3, 64, 64)
    want = net.encode_image(x)
    for name in ("model.safetensors", "open_clip_pytorch_model.bin"):
        got = load_clip(save_weights(net, tmp_path / name)).encode_image(x)
        torch.testing.assert_close(got, want)
    traced = torch.jit.trace_module(net, {"encode_image": x})
    traced.save(str(tmp_path / "ViT-tiny.pt"))
    state, torchscript = load_state_dict(tmp_path / "ViT-tiny.pt", "--clip-weights")
    assert torchscript and load_clip(tmp_path / "ViT-tiny.pt").arch.quick_gelu     # OpenAI's archives: QuickGELU
    (tmp_path / "open_clip_config.json").write_text(json.dumps({"model_cfg": {"quick_gelu": True}}))
    assert load_clip(tmp_path / "model.safetensors").arch.name.endswith("-quickgelu")
    with pytest.raises(FeaturesError, match="QuickGELU"):
        load_clip(tmp_path / "model.safetensors", "ViT-B-16")
    tensors = {"a": torch.randn(3, 2).to(torch.bfloat16), "b": torch.arange(5), "c": torch.tensor([True, False])}
    write_safetensors(tmp_path / "t.safetensors", tensors, {"format": "pt"})
    back = read_safetensors(tmp_path / "t.safetensors")
    assert all(torch.equal(back[k], v) and back[k].dtype == v.dtype for k, v in tensors.items())


def test_tokenizer(tmp_path):
    size = write_vocabulary(tmp_path / "v.txt.gz", ["a wall", "office chair"])
    tok = ClipTokenizer(tmp_path / "v.txt.gz")
    assert tok.size == size
    ids = tok(["A  Wall", "walls!"], 8)
    wall = tok.ids["wall</w>"]
    assert ids[0].tolist() == [tok.start, tok.ids["a</w>"], wall, tok.end, 0, 0, 0, 0]
    assert ids[1, 1:5].tolist() == [tok.ids["wal"], tok.ids["l"], tok.ids["s</w>"], tok.ids["!</w>"]]
    assert tok(["office chair " * 5], 6)[0].tolist()[-1] == tok.end      # cut to fit, end kept
    with pytest.raises(FeaturesError, match="not a gzip"):
        (tmp_path / "bad.gz").write_bytes(b"nope")
        ClipTokenizer(tmp_path / "bad.gz")


def test_query_refuses_another_encoder(tmp_path):
    a, b = tmp_path / "a.bin", tmp_path / "b.bin"
    a.write_bytes(b"weights a")
    b.write_bytes(b"weights b")
    from qr_cl.app.features.weights import file_sha256
    classes = tmp_path / "classes.json"
    classes.write_text(json.dumps({"encoder": {"model": "ViT-B-16", "weights": "a.bin", "sha256": file_sha256(a)},
                                   "classes": []}))
    check_text_encoder(classes, str(a))
    with pytest.raises(QueryError, match="not the CLIP that made"):
        check_text_encoder(classes, str(b))
    classes.write_text(json.dumps({"classes": []}))                    # no record: nothing to check
    check_text_encoder(classes, str(b))
