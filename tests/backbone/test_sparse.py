"""SparseTensor, key packing and kernel maps of backbone.sparse."""

import itertools

import pytest
import torch

from qr_cl.backbone.sparse import (COORD_LIMIT, MAX_BATCH, KernelMapCache, SparseTensor, kernel_offsets,
                                   offset_keys, pack_keys, unpack_keys)


def random_coords(n: int, extent: int, batches: int = 2, multiple: int = 1, seed: int = 0) -> torch.Tensor:
    """Unique random (batch, x, y, z) rows with x, y, z in [-extent, extent), multiples of `multiple`."""
    g = torch.Generator().manual_seed(seed)
    c = torch.cat([torch.randint(0, batches, (n, 1), generator=g), torch.randint(-extent, extent, (n, 3), generator=g)], 1)
    c[:, 1:] *= multiple
    c = torch.unique(c, dim=0)
    return c[torch.randperm(c.shape[0], generator=g)]


def test_pack_unpack_round_trip_and_order():
    c = random_coords(500, 2000)
    c = torch.cat([c, torch.tensor([[MAX_BATCH - 1, COORD_LIMIT, -COORD_LIMIT, 0]])])
    keys = pack_keys(c)
    assert torch.equal(unpack_keys(keys), c)
    lex = sorted(range(c.shape[0]), key=lambda i: tuple(c[i].tolist()))
    assert torch.equal(torch.argsort(keys), torch.tensor(lex))


def test_offset_keys_are_linear():
    c = random_coords(200, 1000)
    d = kernel_offsets(5) * 3
    shifted = c[:, None, 1:] + d[None]
    full = torch.cat([c[:, None, :1].expand(-1, d.shape[0], 1), shifted], 2).reshape(-1, 4)
    assert torch.equal(pack_keys(full).view(c.shape[0], -1), pack_keys(c)[:, None] + offset_keys(d)[None])


def test_kernel_offsets_are_ordered_and_mirrored():
    d = kernel_offsets(3)
    assert d.shape == (27, 3)
    assert torch.equal(d[13], torch.zeros(3, dtype=torch.int64))
    assert torch.equal(d, -d.flip(0))
    assert d.tolist() == [list(t) for t in itertools.product((-1, 0, 1), repeat=3)]


@pytest.mark.parametrize(
    "coords, message",
    [
        (torch.tensor([[0, COORD_LIMIT + 1, 0, 0]]), "coordinates"),
        (torch.tensor([[-1, 0, 0, 0]]), "batch"),
        (torch.tensor([[MAX_BATCH, 0, 0, 0]]), "batch"),
        (torch.zeros(3, 3, dtype=torch.int64), "shape"),
        (torch.zeros(3, 4), "integer"),
    ],
)
def test_pack_keys_rejects_bad_coords(coords, message):
    with pytest.raises(ValueError, match=message):
        pack_keys(coords)


def test_sparse_tensor_rejects_bad_input():
    with pytest.raises(ValueError, match="duplicate"):
        SparseTensor(torch.tensor([[0, 1, 2, 3], [0, 0, 0, 0], [0, 1, 2, 3]]), torch.zeros(3, 2))
    with pytest.raises(ValueError, match="rows"):
        SparseTensor(torch.zeros(3, 4, dtype=torch.int64), torch.zeros(2, 2))
    with pytest.raises(ValueError, match="feats"):
        SparseTensor(torch.zeros(3, 4, dtype=torch.int64), torch.zeros(3))
    with pytest.raises(ValueError, match="multiples"):
        SparseTensor(torch.tensor([[0, 1, 2, 4]]), torch.zeros(1, 2), stride=2)


def brute_force_pairs(coords: torch.Tensor, offsets: torch.Tensor) -> list[set]:
    where = {tuple(r): i for i, r in enumerate(coords.tolist())}
    pairs = []
    for d in offsets.tolist():
        found = set()
        for o, (b, x, y, z) in enumerate(coords.tolist()):
            i = where.get((b, x + d[0], y + d[1], z + d[2]))
            if i is not None:
                found.add((i, o))
        pairs.append(found)
    return pairs


@pytest.mark.parametrize("kernel_size, stride", [(3, 1), (3, 2), (5, 1)])
def test_submanifold_map_matches_brute_force(kernel_size, stride):
    coords = random_coords(300, 6, multiple=stride, seed=kernel_size + stride)
    cache = KernelMapCache()
    cache.register(coords, stride)
    kmap = cache.submanifold(stride, kernel_size)
    expected = brute_force_pairs(coords, kernel_offsets(kernel_size) * stride)
    assert kmap.identity == kernel_size**3 // 2
    for k, want in enumerate(expected):
        if k == kmap.identity:
            assert want == {(i, i) for i in range(coords.shape[0])}
            continue
        got = list(zip(kmap.in_idx[k].tolist(), kmap.out_idx[k].tolist()))
        assert len(got) == len(set(got))
        assert set(got) == want
    assert cache.submanifold(stride, kernel_size) is kmap


def test_downsample_map_assigns_every_voxel_to_its_parent():
    coords = random_coords(400, 9, seed=3)
    cache = KernelMapCache()
    cache.register(coords, 1)
    kmap = cache.downsample(1)
    coarse = cache.coords(2)
    assert kmap.n_in == coords.shape[0] and kmap.n_out == coarse.shape[0]
    assert torch.equal(torch.sort(torch.cat(kmap.in_idx)).values, torch.arange(coords.shape[0]))
    expected_parents = {tuple(r) for r in torch.cat([coords[:, :1], torch.div(coords[:, 1:], 2, rounding_mode="floor") * 2], 1).tolist()}
    assert {tuple(r) for r in coarse.tolist()} == expected_parents
    assert len(expected_parents) == coarse.shape[0]
    for k, (src, dst) in enumerate(zip(kmap.in_idx, kmap.out_idx)):
        child = torch.tensor([k // 4, (k // 2) % 2, k % 2])
        assert torch.equal(coords[src, 0], coarse[dst, 0])
        assert torch.equal(coords[src, 1:], coarse[dst, 1:] + child)
    up = cache.upsample(2)
    assert up.in_idx == kmap.out_idx and up.out_idx == kmap.in_idx


def test_cache_rejects_other_coords_and_missing_levels():
    coords = random_coords(50, 5, seed=1)
    cache = KernelMapCache()
    cache.register(coords, 1)
    cache.register(coords.clone(), 1)
    with pytest.raises(ValueError, match="other coordinates"):
        cache.register(coords[:-1], 1)
    with pytest.raises(KeyError, match="transposed"):
        cache.upsample(2)
    with pytest.raises(ValueError, match="odd"):
        cache.submanifold(1, 2)


def test_empty_level_maps():
    cache = KernelMapCache()
    cache.register(torch.zeros(0, 4, dtype=torch.int64), 1)
    assert all(t.numel() == 0 for t in cache.submanifold(1, 3).in_idx)
    kmap = cache.downsample(1)
    assert kmap.n_in == 0 and kmap.n_out == 0 and cache.coords(2).shape == (0, 4)


@pytest.mark.parametrize("count", [1, 2, 3])
@pytest.mark.parametrize("which", ["submanifold", "down", "up"])
def test_row_blocks_split_the_pairs_by_output_row(count, which):
    cache = KernelMapCache()
    cache.register(random_coords(400, 6, seed=3), 1)
    down = cache.downsample(1)
    kmap = {"submanifold": cache.submanifold(1, 3), "down": down, "up": cache.upsample(2)}[which]
    blocks = kmap.row_blocks(count)
    assert kmap.row_blocks(count) is blocks and len(blocks) == count
    assert [b.start for b in blocks] == [0] + [b.stop for b in blocks[:-1]] and blocks[-1].stop == kmap.n_out
    pairs = [b.stop - b.start if kmap.identity is not None else 0 for b in blocks]
    def offset(block, k):
        return block.in_rows[block.bounds[k]:block.bounds[k + 1]], block.out_rows[block.bounds[k]:block.bounds[k + 1]]

    for k in range(kmap.volume):
        src = torch.cat([offset(b, k)[0] for b in blocks])
        dst = torch.cat([offset(b, k)[1] + b.start for b in blocks])
        assert count > 1 or torch.equal(src, kmap.in_idx[k])
        order = torch.argsort(kmap.out_idx[k], stable=True)
        mine = torch.argsort(dst, stable=True)
        assert torch.equal(src[mine], kmap.in_idx[k][order]) and torch.equal(dst[mine], kmap.out_idx[k][order])
        for i, b in enumerate(blocks):
            assert bool(((offset(b, k)[1] >= 0) & (offset(b, k)[1] < b.stop - b.start)).all())
            pairs[i] += offset(b, k)[0].numel()
    assert sum(pairs) == kmap.pairs
    degree = 27 if which == "submanifold" else 8
    assert max(pairs) - min(pairs) <= 2 * degree          # balanced to within a row's pairs or two


def test_transposed_map_is_kept():
    cache = KernelMapCache()
    cache.register(random_coords(100, 5, seed=4), 1)
    down = cache.downsample(1)
    assert cache.upsample(2) is cache.upsample(2) is down.transposed()
    assert down.transposed().transposed().in_idx is down.in_idx
