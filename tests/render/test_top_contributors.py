"""qr_cl.rasterize_top_contributing_gaussian_ids (gsplat's name, argument order and shapes):
the K picks of a sampler per pixel from rasterization's meta, dense or packed, with V-Render's
weights alpha_i T_i, against the V-Render twin and the renders' own selections."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import qr_cl
from tests.render.test_rasterization import tensors, turned_cameras
from tests.twins import top_contributors

K = 4


def meta_of(scene, packed: bool, sampler: str = "volume", k: int = 40):
    m, q, s, o, v, K_, w, h = scene
    viewmats, Ks = turned_cameras(v, K_)
    colors = np.random.default_rng(0).random((len(m), 3)).astype(np.float32)
    return qr_cl.rasterization(*tensors(m, q, s, o, colors), viewmats, Ks, w, h, packed=packed, sampler=sampler,
                               k=k)[2]


def query(meta, k: int = K, sampler: str = "topk"):
    return qr_cl.rasterize_top_contributing_gaussian_ids(
        meta["means2d"], meta["conics"], meta["opacities"], meta["isect_offsets"], meta["flatten_ids"],
        meta["width"], meta["height"], meta["tile_size"], k, sampler=sampler)


def padded_ids(sel, k: int) -> np.ndarray:
    ids = sel.host()["ids"]
    return np.pad(ids, ((0, 0), (0, k - ids.shape[1])), constant_values=-1)


def test_top_k_equals_the_volume_twin_and_the_topk_sampler(random_scene):
    meta = meta_of(random_scene, packed=False)
    ids, weights = query(meta)
    w, h = meta["width"], meta["height"]
    assert ids.shape == weights.shape == (2, h, w, K) and ids.dtype == torch.int32 and weights.dtype == torch.float32
    assert not ids.requires_grad and not weights.requires_grad
    topk = meta_of(random_scene, packed=False, sampler="topk", k=K)["selections"]
    for c in range(2):
        want_ids, want_w = top_contributors(meta["selections"][c].plan.meta(), w, h, K)
        got_ids, got_w = ids[c].reshape(-1, K).numpy(), weights[c].reshape(-1, K).numpy()
        flipped = (got_ids != want_ids).any(1)
        assert flipped.mean() <= 0.001, f"{flipped.sum()} pixels pick other Gaussians than the twin"
        np.testing.assert_allclose(got_w[~flipped], want_w[~flipped], rtol=1e-5, atol=1e-6)
        np.testing.assert_array_equal(got_ids, padded_ids(topk[c], K))      # the topk sampler's picks
    assert (weights[ids < 0] == 0).all() and (weights[ids >= 0] > 0).all()
    assert (ids[..., 0] >= 0).float().mean() > 0.3 and (ids[..., -1] < 0).any()


def test_weights_are_the_volume_composite(random_scene):
    """The weights of a pixel's picks are among its V-Render weights, and sum to at most its alpha."""
    m, q, s, o, v, K_, w, h = random_scene
    _, alpha, meta = qr_cl.rasterization(*tensors(m, q, s, o, np.ones((len(m), 3))), torch.tensor(v)[None],
                                         torch.tensor(K_)[None], w, h, packed=False)
    _, weights = query(meta, k=40)
    assert (weights.sum(-1) <= alpha[..., 0] + 1e-5).all()
    torch.testing.assert_close(weights.sum(-1), alpha[..., 0], atol=1e-5, rtol=1e-5)   # K = 40: every one


@pytest.mark.parametrize("sampler", ["quantile", "stratified"])
def test_other_samplers_pick_their_selection(random_scene, sampler):
    meta = meta_of(random_scene, packed=False)
    ids, weights = query(meta, sampler=sampler)
    picks = meta_of(random_scene, packed=False, sampler=sampler, k=K)["selections"]
    w, h = meta["width"], meta["height"]
    for c in range(2):
        np.testing.assert_array_equal(ids[c].reshape(-1, K).numpy(), padded_ids(picks[c], K))
        volume = meta["selections"][c].host()
        for p in np.random.default_rng(c).choice(w * h, 200, replace=False):
            for g, wt in zip(ids[c].reshape(-1, K)[p].numpy(), weights[c].reshape(-1, K)[p].numpy()):
                if g >= 0:
                    assert wt == volume["weights"][p][list(volume["ids"][p]).index(g)]


def test_packed_meta_gives_packed_rows(random_scene):
    dense, packed = meta_of(random_scene, packed=False), meta_of(random_scene, packed=True)
    d_ids, d_w = query(dense)
    p_ids, p_w = query(packed)
    assert torch.equal(d_w, p_w)
    rows = p_ids.long()
    gaussian = torch.where(rows >= 0, packed["gaussian_ids"][rows.clamp(min=0)], -1)
    camera = packed["camera_ids"][rows.clamp(min=0)]
    assert torch.equal(gaussian.int(), d_ids)
    assert (camera[rows >= 0] == torch.arange(2)[:, None, None, None].expand_as(rows)[rows >= 0]).all()


def test_gpu_launch_shapes_give_the_same_bytes(random_scene, monkeypatch):
    from qr_cl.runtime import runtime
    out = {}
    for launch in ("cpu", "gpu"):
        monkeypatch.setattr(runtime(), "gpu_shaped", launch == "gpu")
        meta = meta_of(random_scene, packed=True)
        out[launch] = [t.numpy().tobytes() for t in (*query(meta), *query(meta, sampler="quantile"))]
    assert out["gpu"] == out["cpu"]


def test_refusals_are_named(random_scene):
    meta = meta_of(random_scene, packed=False)
    with pytest.raises(ValueError, match="tile_size"):
        qr_cl.rasterize_top_contributing_gaussian_ids(meta["means2d"], meta["conics"], meta["opacities"],
                                                      meta["isect_offsets"], meta["flatten_ids"], meta["width"],
                                                      meta["height"], 8, K)
    with pytest.raises(ValueError, match="volume"):
        query(meta, sampler="volume")
    with pytest.raises(ValueError, match="k must be"):
        query(meta, k=0)
    with pytest.raises(ValueError, match="isect_offsets"):
        qr_cl.rasterize_top_contributing_gaussian_ids(meta["means2d"], meta["conics"], meta["opacities"],
                                                      meta["isect_offsets"], meta["flatten_ids"], meta["width"] + 40,
                                                      meta["height"], 16, K)


def test_no_gaussians_pick_nothing(random_scene):
    m, q, s, o, v, K_, w, h = random_scene
    for packed in (False, True):
        meta = qr_cl.rasterization(torch.zeros(0, 3), torch.zeros(0, 4), torch.zeros(0, 3), torch.zeros(0),
                                   torch.zeros(0, 3), torch.tensor(v)[None], torch.tensor(K_)[None], w, h,
                                   packed=packed)[2]
        ids, weights = query(meta)
        assert ids.shape == (1, h, w, K) and (ids == -1).all() and (weights == 0).all()
