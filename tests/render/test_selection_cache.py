"""The optional selection cache: same results, hits on repeated views, bounded in bytes."""
import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.render import SelectionCache, rasterize_plan
from qr_cl.stages import select


def render(scene, cache, viewmat=None, sampler="quantile", k=8):
    means, quats, scales, opacities, view, K, w, h = scene
    feats = torch.from_numpy(np.random.default_rng(0).random((len(means), 5), dtype=np.float32))
    feats.requires_grad_(True)
    img, alpha, meta = qr_cl.rasterize(means, quats, scales, opacities, feats,
                                       view if viewmat is None else viewmat, K, w, h,
                                       sampler=sampler, k=k, cache=cache)
    img.sum().backward()
    return img.detach(), feats.grad, meta["selection"]


def shifted(scene, dx):
    view = scene[4].copy()
    view[0, 3] += dx
    return view


def test_cached_render_equals_uncached_and_hits(random_scene):
    cache = SelectionCache(max_bytes=64 << 20)
    plain_img, plain_grad, _ = render(random_scene, None)
    img1, grad1, sel1 = render(random_scene, cache)
    img2, grad2, sel2 = render(random_scene, cache)
    assert sel2 is sel1 and (cache.hits, cache.misses, len(cache)) == (1, 1, 1)
    assert torch.equal(img1, plain_img) and torch.equal(img2, plain_img)
    assert torch.equal(grad1, plain_grad) and torch.equal(grad2, plain_grad)
    render(random_scene, cache, sampler="topk")          # another sampler: a miss
    render(random_scene, cache, viewmat=shifted(random_scene, 0.1))   # another camera: a miss
    assert (cache.hits, cache.misses, len(cache)) == (1, 3, 3)


def test_cache_is_bounded_in_bytes_lru(random_scene):
    _, _, sel = render(random_scene, None)
    one = SelectionCache._size(sel)
    cache = SelectionCache(max_bytes=int(2.5 * one))
    views = [shifted(random_scene, dx) for dx in (0.0, 0.05, 0.1)]
    for v in views:
        render(random_scene, cache, viewmat=v)
    assert len(cache) == 2 and cache.nbytes <= cache.max_bytes
    render(random_scene, cache, viewmat=views[2])        # the newest is kept
    render(random_scene, cache, viewmat=views[0])        # the oldest was evicted
    assert (cache.hits, cache.misses) == (1, 4)
    tiny = SelectionCache(max_bytes=16)
    render(random_scene, tiny)
    assert len(tiny) == 0                                # larger than the bound: not kept
    with pytest.raises(ValueError, match="positive"):
        SelectionCache(0)


def test_get_if_room_keeps_what_fits_and_evicts_nothing(random_scene):
    plan = rasterize_plan(*random_scene)

    def make():
        return select(plan, "quantile", 8)
    one = SelectionCache._size(make())
    cache = SelectionCache(max_bytes=int(1.5 * one))
    first = cache.get_if_room(("room", 0, "quantile", 8), make)
    assert cache.get_if_room(("room", 0, "quantile", 8), make) is first and len(cache) == 1
    assert cache.get_if_room(("room", 1, "quantile", 8), make) is None     # no room: the caller selects
    assert len(cache) == 1 and (cache.hits, cache.misses, cache.refused) == (1, 2, 1)
    tiny = SelectionCache(max_bytes=16)
    assert tiny.get_if_room("a", make) is not None and len(tiny) == 0     # made, too large to keep
    assert tiny.get_if_room("b", make) is None
    assert tiny.refused == 2
