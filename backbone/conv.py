"""Sparse 3D convolutions, batch norm and ReLU on :class:`~backbone.sparse.SparseTensor`.

A convolution gathers the input rows of each kernel offset k's pairs, multiplies them by the
``[C_in, C_out]`` weight of k and ``index_add_``-s the products into the output rows, in pair
order, so that each output row sums its terms in offset order. Offsets are taken in chunks of
about :data:`CHUNK_BYTES` (one gather and one ``index_add_`` per chunk, one product per offset,
in reused per-thread scratch memory). The backward pass is the same operation on the transposed
map with transposed weights (no float atomics, no saved gathers), sharing each chunk's gathered
output gradient with the weight gradient, one ``[C_in, P_k] @ [P_k, C_out]`` product per offset.

Both cores: a map with at least :data:`MIN_SPLIT_PAIRS` pairs is split into :data:`SPLIT` blocks
of consecutive output rows with about equal pairs (:meth:`~backbone.sparse.KernelMap.row_blocks`,
built once per map). A block's rows are written by one task only, so the blocks run on
:func:`set_conv_threads` threads (the caller's and helpers') without locks or atomics; the weight
gradient is summed over the blocks in block order. The split depends on the map only, never on
the thread count, so results are bitwise the same on 1 or 2 threads and run to run. The forward
is also bitwise that of the whole map at once (with MKL a row of a product does not depend on
the other rows; the tests check it), the backward equal to it up to float rounding (other
summation orders). Torch's own intra-op threads (OpenMP) spin at barriers and were slow beside
other busy processes; these helpers sleep in a queue instead, and a block that no helper has
started when the caller is done with its own (its core busy elsewhere) is run by the caller.

Weights are stored ``[K, C_in, C_out]`` with offsets ordered like
:func:`~backbone.sparse.kernel_offsets` (dx, dy, dz lexicographic, dz fastest). The equivalent
dense weight is ``weight.reshape(k, k, k, C_in, C_out).permute(4, 3, 0, 1, 2)`` for
``torch.nn.functional.conv3d`` and ``.permute(3, 4, 0, 1, 2)`` for ``conv_transpose3d``.
"""

from __future__ import annotations

import math
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from functools import partial
from typing import Callable, Iterator, Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.autograd.function import once_differentiable

from .sparse import KernelMap, RowBlock, SparseTensor

#: Row blocks of a map that has at least :data:`MIN_SPLIT_PAIRS` pairs (fixed: results depend on it).
SPLIT = 2
#: Pairs (identity rows included) from which a map is split into row blocks; smaller maps run
#: whole, where a block's fixed cost (torch calls, a thread hand-over) would outweigh its share.
MIN_SPLIT_PAIRS = 4096
#: Bytes of gathered and product rows per chunk of offsets (one gather and one scatter each):
#: fewer, larger ops than one per offset, small enough to stay in cache.
CHUNK_BYTES = 1 << 22

_arena = threading.local()
_lock = threading.Lock()
_threads = 1
_helpers: ThreadPoolExecutor | None = None
_helper_setup = (0, 0)      # (helpers, torch intra-op threads) of the running helpers


def set_conv_threads(threads: int) -> None:
    """Run sparse convolutions on ``threads`` threads: the calling one and ``threads - 1`` helpers
    (at most :data:`SPLIT` are used). Results do not depend on it. Each helper runs torch with the
    caller's intra-op thread count at this call (a new thread would otherwise take OpenMP's
    default, every core), so ``threads * torch.get_num_threads()`` should not exceed the cores."""
    global _threads, _helpers, _helper_setup
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    with _lock:
        helpers = min(threads, SPLIT) - 1
        setup = (helpers, torch.get_num_threads() if helpers else 0)
        if setup != _helper_setup:
            if _helpers is not None:
                _helpers.shutdown(wait=True)
            _helpers = ThreadPoolExecutor(helpers, thread_name_prefix="qr-cl-conv", initializer=torch.set_num_threads,
                                          initargs=(setup[1],)) if helpers else None
            _helper_setup = setup
        _threads = threads


def get_conv_threads() -> int:
    """Threads sparse convolutions run on (:func:`set_conv_threads`; 1 unless set)."""
    return _threads


@contextmanager
def conv_threads(threads: int) -> Iterator[None]:
    """Run the block with :func:`set_conv_threads` ``(threads)``, restoring the previous count after."""
    old = get_conv_threads()
    set_conv_threads(threads)
    try:
        yield
    finally:
        set_conv_threads(old)


def _without_grad(task: Callable[[], None]) -> None:
    with torch.no_grad():
        task()


def run_tasks(tasks: list[Callable[[], None]]) -> None:
    """Run independent tasks (disjoint outputs) on the :func:`set_conv_threads` threads: the
    first on this thread, the others on the helpers; one that no helper has started when this
    thread is done is run here. With one thread they run here in order."""
    helpers = _helpers
    if helpers is None or len(tasks) == 1:
        for task in tasks:
            task()
        return
    futures = [helpers.submit(_without_grad, task) for task in tasks[1:]]
    try:
        tasks[0]()
    finally:
        for future, task in zip(futures, tasks[1:]):
            if future.cancel():
                task()
            else:
                future.result()


def _blocks(kmap: KernelMap) -> tuple[RowBlock, ...]:
    """The row blocks a convolution with ``kmap`` runs as (a function of the map only)."""
    return kmap.row_blocks(SPLIT if kmap.pairs >= MIN_SPLIT_PAIRS else 1)


def _scratch(rows: int, cols: int, dtype: torch.dtype, slot: int) -> Tensor:
    """An uninitialised ``[rows, cols]`` view of this thread's scratch buffer ``slot`` (0 or 1),
    grown when too small and kept: no fresh pages to fault in on every call. A thread runs one
    block at a time, so a slot is never in use twice."""
    buffers = _arena.__dict__.setdefault("buffers", {})
    size = rows * cols
    buffer = buffers.get((slot, dtype))
    if buffer is None or buffer.numel() < size:
        buffer = buffers[(slot, dtype)] = torch.empty(size, dtype=dtype)
    return buffer[:size].view(rows, cols)


def _chunks(bounds: tuple[int, ...], row_bytes: int) -> list[tuple[int, int, list[int]]]:
    """Consecutive offset ranges ``[k0, k1)`` whose pairs take about :data:`CHUNK_BYTES` of
    gathered and product rows (``row_bytes`` per pair), at least one offset each, with the
    number of pairs of each of their offsets."""
    chunks, first = [], 0
    for k in range(1, len(bounds)):
        if (bounds[k] - bounds[first]) * row_bytes >= CHUNK_BYTES or k == len(bounds) - 1:
            chunks.append((first, k, [bounds[i + 1] - bounds[i] for i in range(first, k)]))
            first = k
    return chunks


def _conv_rows(
    feats: Tensor, weights: Sequence[Tensor], block: RowBlock, identity: int | None, out: Tensor
) -> None:
    """Rows ``[block.start, block.stop)`` of the convolution of ``feats`` ``[n_in, C_in]`` with
    ``weights`` (K of ``[C_in, C_out]``) into ``out``: the identity's product, then for each chunk
    of offsets one gather of its pairs' input rows, a product per offset and one ``index_add_``
    in pair order (so a row's sum is taken in offset order)."""
    rows = out[block.start : block.stop]
    if identity is not None:
        torch.mm(feats[block.start : block.stop], weights[identity], out=rows)
    else:
        rows.zero_()
    c_in, c_out = weights[0].shape
    for k0, k1, sizes in _chunks(block.bounds, (c_in + c_out) * feats.element_size()):
        a, b = block.bounds[k0], block.bounds[k1]
        if b == a:
            continue
        gathered = _scratch(b - a, c_in, feats.dtype, 0)
        torch.index_select(feats, 0, block.in_rows[a:b], out=gathered)
        products = _scratch(b - a, c_out, feats.dtype, 1)
        for k, g, p in zip(range(k0, k1), gathered.split(sizes), products.split(sizes)):
            if k != identity and g.shape[0]:
                torch.mm(g, weights[k], out=p)
        rows.index_add_(0, block.out_rows[a:b], products)


def _grad_rows(
    grad_out: Tensor,
    feats: Tensor,
    weights_t: Sequence[Tensor],
    block: RowBlock,
    identity: int | None,
    grad_feats: Tensor | None,
    grad_weight: Sequence[Tensor] | None,
) -> None:
    """The backward of the pairs of ``block``, a block of the transposed map (``in_rows``: output
    rows, ``out_rows``: input rows minus ``start``): rows ``[start, stop)`` of ``grad_feats``
    (as :func:`_conv_rows` with ``weights_t``, K of ``[C_out, C_in]``) and these pairs' share of
    the weight gradient into ``grad_weight`` (K of ``[C_in, C_out]``); a chunk's gathered output
    gradient serves both. Either output may be None (not needed)."""
    start, stop = block.start, block.stop
    c_out, c_in = weights_t[0].shape
    rows = None if grad_feats is None else grad_feats[start:stop]
    if identity is not None:
        if rows is not None:
            torch.mm(grad_out[start:stop], weights_t[identity], out=rows)
        if grad_weight is not None:
            torch.mm(feats[start:stop].t(), grad_out[start:stop], out=grad_weight[identity])
    elif rows is not None:
        rows.zero_()
    for k0, k1, sizes in _chunks(block.bounds, (c_in + c_out) * feats.element_size()):
        a, b = block.bounds[k0], block.bounds[k1]
        gathered = _scratch(b - a, c_out, grad_out.dtype, 0)
        torch.index_select(grad_out, 0, block.in_rows[a:b], out=gathered)
        inputs = _scratch(b - a, c_in, feats.dtype, 1)
        if rows is not None and b > a:
            for k, g, p in zip(range(k0, k1), gathered.split(sizes), inputs.split(sizes)):
                if k != identity and g.shape[0]:
                    torch.mm(g, weights_t[k], out=p)
            rows.index_add_(0, block.out_rows[a:b], inputs)
        if grad_weight is not None:
            torch.index_select(feats[start:stop], 0, block.out_rows[a:b], out=inputs)
            for k, g, f in zip(range(k0, k1), gathered.split(sizes), inputs.split(sizes)):
                if k != identity:
                    torch.mm(f.t(), g, out=grad_weight[k])


def _apply_map(feats: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
    """Sum over offsets k of ``feats[in_idx[k]] @ weight[k]`` added into rows ``out_idx[k]`` of
    ``[n_out, C_out]``, block by block on the convolution threads."""
    out = feats.new_empty(kmap.n_out, weight.shape[2])
    weights = weight.unbind(0)
    run_tasks([partial(_conv_rows, feats, weights, block, kmap.identity, out) for block in _blocks(kmap)])
    return out


class _SparseConvFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, feats: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
        ctx.save_for_backward(feats, weight)
        ctx.kmap = kmap
        return _apply_map(feats, weight, kmap)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: Tensor):
        feats, weight = ctx.saved_tensors
        kmap: KernelMap = ctx.kmap
        grad_out = grad_out.contiguous()
        need_feats, need_weight = ctx.needs_input_grad[:2]
        blocks = _blocks(kmap.transposed())
        grad_feats = feats.new_empty(kmap.n_in, feats.shape[1]) if need_feats else None
        shares = weight.new_empty(len(blocks), *weight.shape) if need_weight else None
        weights_t = weight.transpose(1, 2).unbind(0)
        run_tasks(
            [
                partial(_grad_rows, grad_out, feats, weights_t, block, kmap.identity, grad_feats,
                        None if shares is None else shares[b].unbind(0))
                for b, block in enumerate(blocks)
            ]
        )
        return grad_feats, None if shares is None else shares.sum(0), None


def sparse_conv(feats: Tensor, weight: Tensor, kmap: KernelMap) -> Tensor:
    """Apply a kernel map: feats ``[n_in, C_in]``, weight ``[K, C_in, C_out]`` -> ``[n_out, C_out]``."""
    if feats.dim() != 2 or feats.shape[0] != kmap.n_in:
        raise ValueError(f"feats must have shape [{kmap.n_in}, C_in], got {list(feats.shape)}")
    if weight.dim() != 3 or weight.shape[0] != kmap.volume or weight.shape[1] != feats.shape[1]:
        raise ValueError(
            f"weight must have shape [{kmap.volume}, {feats.shape[1]}, C_out], got {list(weight.shape)}"
        )
    return _SparseConvFunction.apply(feats.contiguous(), weight, kmap)


class _SparseConvBase(nn.Module):
    def __init__(self, in_channels: int, out_channels: int, volume: int, bias: bool) -> None:
        super().__init__()
        self.in_channels = in_channels
        self.out_channels = out_channels
        self.weight = nn.Parameter(torch.empty(volume, in_channels, out_channels))
        self.bias = nn.Parameter(torch.empty(out_channels)) if bias else None
        bound = 1.0 / math.sqrt(volume * in_channels)
        nn.init.uniform_(self.weight, -bound, bound)
        if self.bias is not None:
            nn.init.uniform_(self.bias, -bound, bound)

    def _run(self, x: SparseTensor, kmap: KernelMap) -> Tensor:
        out = sparse_conv(x.feats, self.weight, kmap)
        return out if self.bias is None else out + self.bias

    def extra_repr(self) -> str:
        return f"{self.in_channels}, {self.out_channels}, offsets={self.weight.shape[0]}, bias={self.bias is not None}"


class SubmanifoldConv3d(_SparseConvBase):
    """Convolution with a centred odd kernel whose output sites are its input sites.

    Input ``[M, C_in]`` at stride s -> output ``[M, C_out]`` at stride s; neighbours are
    ``kernel_size`` voxels of the tensor's stride apart (a dilation of s in finest voxels).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: int = 3, bias: bool = False) -> None:
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd and >= 1, got {kernel_size}")
        super().__init__(in_channels, out_channels, kernel_size**3, bias)
        self.kernel_size = kernel_size

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(self._run(x, x.cache.submanifold(x.stride, self.kernel_size)))


class DownsampleConv3d(_SparseConvBase):
    """Kernel-2 stride-2 convolution: stride s -> 2s, one output per occupied parent cell."""

    def __init__(self, in_channels: int, out_channels: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 8, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        kmap = x.cache.downsample(x.stride)
        coarse = 2 * x.stride
        return SparseTensor(x.cache.coords(coarse), self._run(x, kmap), coarse, x.cache)


class UpsampleConv3d(_SparseConvBase):
    """Kernel-2 stride-2 transposed convolution: stride s -> s/2 on the exact finer coordinates.

    The finer coordinates are those that were down-sampled to this tensor's through its cache.
    """

    def __init__(self, in_channels: int, out_channels: int, bias: bool = False) -> None:
        super().__init__(in_channels, out_channels, 8, bias)

    def forward(self, x: SparseTensor) -> SparseTensor:
        kmap = x.cache.upsample(x.stride)
        fine = x.stride // 2
        return SparseTensor(x.cache.coords(fine), self._run(x, kmap), fine, x.cache)


class SparseBatchNorm(nn.BatchNorm1d):
    """BatchNorm over all voxels of a batch (features ``[M, C]``).

    In training mode with fewer than two voxels, where batch statistics do not exist, it normalizes
    with the running statistics and leaves them unchanged.
    """

    def forward(self, x: SparseTensor) -> SparseTensor:
        if self.training and len(x) < 2:
            feats = F.batch_norm(x.feats, self.running_mean, self.running_var, self.weight, self.bias, False, 0.0, self.eps)
        else:
            feats = super().forward(x.feats)
        return x.with_feats(feats)


class SparseReLU(nn.Module):
    """ReLU on the features."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(F.relu(x.feats))


class SparseLinear(nn.Linear):
    """Per-voxel linear map (a 1x1x1 convolution), ``[M, C_in]`` -> ``[M, C_out]``."""

    def forward(self, x: SparseTensor) -> SparseTensor:
        return x.with_feats(super().forward(x.feats))
