"""Subsets and compact tables of selections (training's selections) against numpy twins:
gather_rays (rays of a whole-image selection), remap_ids / compact_selections (ids re-indexed into
the Gaussians used) and concat_selections (several views' rays as one selection)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from qr_cl.render import blend, rasterize_plan
from qr_cl.stages import (compact_selections, concat_selections, derived, gather_rays, listed_selection, ray_entries,
                          remap_ids, select)

SAMPLERS = [("quantile", 6), ("topk", 3), ("volume", 0)]


@pytest.fixture(scope="module")
def plan(random_scene):
    return rasterize_plan(*random_scene)


def random_pixels(plan, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.stack([rng.integers(0, plan.width, n), rng.integers(0, plan.height, n)], 1).astype(np.int32)


def entries_twin(offsets: np.ndarray, count: np.ndarray) -> np.ndarray:
    """ray_entries written as a loop."""
    return np.array([o + j for o, c in zip(offsets, count) for j in range(c)], np.int64)


def test_ray_entries_matches_loop():
    rng = np.random.default_rng(0)
    count = rng.integers(0, 5, 40)
    offsets = rng.permutation(200)[:40] * 6
    np.testing.assert_array_equal(ray_entries(offsets, count), entries_twin(offsets, count))
    assert ray_entries(np.zeros(0, np.int32), np.zeros(0, np.int32)).shape == (0,)


@pytest.mark.parametrize("sampler,k", SAMPLERS)
def test_gather_rays_equals_selecting_the_pixels(plan, sampler, k):
    whole = select(plan, sampler, k)
    pixels = random_pixels(plan, 300, 1)
    rays = pixels[:, 1].astype(np.int64) * plan.width + pixels[:, 0]
    got = gather_rays(whole, rays)
    np.testing.assert_array_equal(got.pixels, pixels)
    host, want, twin = got.host(), select(plan, sampler, k, pixels).host(), whole.host()
    for name in host:                                  # the kernel on those pixels, bit for bit
        np.testing.assert_array_equal(host[name], want[name], err_msg=name)
    for name in ("count", "t_walk", "t_sel", "t_rem"):  # numpy twin: the whole image's rows
        np.testing.assert_array_equal(host[name], twin[name][rays], err_msg=name)
    width = host["ids"].shape[1]
    np.testing.assert_array_equal(host["ids"], twin["ids"][rays, :width])
    np.testing.assert_array_equal(host["weights"], twin["weights"][rays, :width])


def test_gather_rays_of_a_subset_and_of_none(plan):
    pixels = random_pixels(plan, 50, 2)
    sub = select(plan, "quantile", 4, pixels)
    pick = np.array([3, 3, 0, 49])
    got = gather_rays(sub, pick)
    np.testing.assert_array_equal(got.pixels, pixels[pick])
    for name, value in got.host().items():
        np.testing.assert_array_equal(value, select(plan, "quantile", 4, pixels[pick]).host()[name], err_msg=name)
    assert gather_rays(sub, np.zeros(0, np.int64)).n_rays == 0
    with pytest.raises(ValueError, match="index"):
        gather_rays(sub, np.array([50]))


@pytest.mark.parametrize("sampler,k", SAMPLERS)
def test_remap_ids_matches_numpy(plan, sampler, k):
    sel = select(plan, sampler, k, random_pixels(plan, 200, 3))
    n = plan.n_gaussians
    lut = np.random.default_rng(4).permutation(n).astype(np.int32)
    got = remap_ids(sel, lut, n)
    assert got.n_rows == got.n_gaussians == n and sel.n_rows is None
    before, after = sel.host(), got.host()
    valid = before["ids"] >= 0
    np.testing.assert_array_equal(after["ids"], np.where(valid, lut[np.maximum(before["ids"], 0)], -1))
    np.testing.assert_array_equal(after["weights"], before["weights"])
    with pytest.raises(ValueError, match="outside"):
        remap_ids(sel, lut, 1)


@pytest.mark.parametrize("sampler,k", SAMPLERS)
def test_compact_selections_render_and_backprop_like_the_full_table(plan, sampler, k):
    sels = [select(plan, sampler, k, random_pixels(plan, 150, s)) for s in (5, 6)]
    rows, compact = compact_selections(sels)
    used = np.concatenate([h["ids"][h["ids"] >= 0] for h in (s.host() for s in sels)])
    np.testing.assert_array_equal(rows, np.unique(used))       # numpy twin of the union
    assert all(c.n_gaussians == len(rows) for c in compact)
    full = torch.randn(plan.n_gaussians, 20, generator=torch.Generator().manual_seed(0), requires_grad=True)
    table = full.detach()[torch.from_numpy(rows)].requires_grad_()
    grads = [torch.randn(s.n_rays, 20, generator=torch.Generator().manual_seed(i)) for i, s in enumerate(sels)]
    for sel, small, g in zip(sels, compact, grads):
        image, small_image = blend(sel, full), blend(small, table)
        assert torch.equal(image, small_image)
        image.backward(g)
        small_image.backward(g)
    assert torch.equal(full.grad[torch.from_numpy(rows)], table.grad)
    rest = np.setdiff1d(np.arange(plan.n_gaussians), rows)
    assert not full.grad[torch.from_numpy(rest)].any()


@pytest.mark.parametrize("sampler,k", SAMPLERS)
def test_concat_selections_stacks_the_rays(plan, sampler, k):
    sels = [select(plan, sampler, k, random_pixels(plan, n, s)) for n, s in ((120, 7), (0, 8), (90, 9))]
    both = concat_selections(sels)
    assert both.n_rays == 210
    parts = [s.host() for s in sels if s.n_rays]
    got = both.host()
    for name in ("count", "t_walk", "t_sel", "t_rem"):
        np.testing.assert_array_equal(got[name], np.concatenate([p[name] for p in parts]), err_msg=name)
    width = got["ids"].shape[1]
    pad = lambda a, v: np.pad(a, ((0, 0), (0, width - a.shape[1])), constant_values=v)
    np.testing.assert_array_equal(got["ids"], np.concatenate([pad(p["ids"], -1) for p in parts]))
    np.testing.assert_array_equal(got["weights"], np.concatenate([pad(p["weights"], 0) for p in parts]))
    features = torch.randn(plan.n_gaussians, 24, generator=torch.Generator().manual_seed(1))
    assert torch.equal(blend(both, features), torch.cat([blend(s, features) for s in sels]))
    rows, (small,) = compact_selections([both])
    assert concat_selections([small, small]).n_rows == small.n_rows
    with pytest.raises(ValueError, match="pixel subsets"):
        concat_selections([select(plan, sampler, k)])


@pytest.mark.parametrize("n_rays,k", [(40, 5), (7, 1), (0, 3), (6, 0)])
def test_listed_selection_holds_the_lists_and_blends_them(plan, n_rays, k):
    """A selection of given lists (-1 padded at the end) has those entries (host()), blends as the
    numpy twin sum_j w[p,j] f[id[p,j]] and its backward is the transpose sum over the entries of
    w dImage[p]; no rays and no slots are selections too."""
    rng = np.random.default_rng(n_rays + k)
    pixels = random_pixels(plan, n_rays, 3)
    ids = rng.integers(0, plan.n_gaussians, (n_rays, k))
    count = rng.integers(0, k + 1, n_rays)
    ids[np.arange(k)[None] >= count[:, None]] = -1
    weights = np.where(ids >= 0, rng.random((n_rays, k)), 0).astype(np.float32)
    sel = listed_selection(plan, pixels, ids, weights)
    host = sel.host()
    np.testing.assert_array_equal(host["count"], count)
    np.testing.assert_array_equal(host["ids"], ids[:, :host["ids"].shape[1]])
    np.testing.assert_array_equal(host["weights"], weights[:, :host["weights"].shape[1]])
    features = torch.from_numpy(rng.standard_normal((plan.n_gaussians, 5)).astype(np.float32)).requires_grad_()
    image = blend(sel, features)
    f = features.detach().numpy().astype(np.float64)
    want = np.einsum("pk,pkc->pc", weights, np.where((ids >= 0)[..., None], f[np.maximum(ids, 0)], 0))
    np.testing.assert_allclose(image.detach().numpy(), want, rtol=1e-5, atol=1e-6)
    dimage = rng.standard_normal((n_rays, 5))
    image.backward(torch.from_numpy(dimage.astype(np.float32)))
    want_grad = np.zeros((plan.n_gaussians, 5))
    np.add.at(want_grad, ids[ids >= 0], weights[ids >= 0][:, None] * np.repeat(dimage, k, 0).reshape(n_rays, k, 5)[ids >= 0])
    np.testing.assert_allclose(features.grad.numpy(), want_grad, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="one row per pixel"):
        listed_selection(plan, pixels, ids[:, :k - 1] if k else ids[:0], weights)
