"""Shared blend (blend.cl) and its backward against numpy references."""
from __future__ import annotations

import numpy as np
import pyopencl.array as cla
import pytest

from qr_cl.render import rasterize_plan
from qr_cl.runtime import channel_layout, memory, padded_rows, shared_array
from qr_cl.stages import blend as blend_stage
from qr_cl.stages import blend_backward, blend_forward, blend_ref, render_fused, select, select_and_blend

RTOL = 1e-5


def assert_rows_close(got: np.ndarray, want: np.ndarray, scale: np.ndarray, rtol: float = RTOL) -> None:
    """Element-wise |got - want| <= rtol * scale: scale [P,1] is the ray's sum of absolute
    contributions (the conditioning of a sum of signed terms)."""
    bad = np.abs(got - want) > rtol * scale + 1e-12
    assert not bad.any(), f"{bad.sum()} elements differ, worst {np.abs(got - want)[bad].max()}"


@pytest.mark.parametrize("channels,nv", [(1, 1), (37, 3), (64, 4), (496, 31), (512, 32), (2048, 32)])
def test_cpu_work_items_take_the_largest_row_part_that_divides_it(channels, nv):
    """CPU shapes accumulate the largest divisor of the row's vectors up to CPU_ROW_VECTORS (a
    whole 512-float row); GPU shapes one vector; the padded row length does not depend on it."""
    vw, cpu_nv, cstride = channel_layout(channels)
    assert cpu_nv == nv and cstride % (vw * nv) == 0 and cstride - channels < vw
    assert channel_layout(channels, gpu_shaped=True) == (vw, 1, cstride)


@pytest.fixture(scope="module")
def plan(random_scene):
    return rasterize_plan(*random_scene)


def device_rows(plan, array: np.ndarray) -> cla.Array:
    return cla.to_device(plan.runtime.queue, padded_rows(array, channel_layout(array.shape[1])[2]))


@pytest.mark.parametrize("sampler,k", [("quantile", 1), ("quantile", 10), ("topk", 10), ("volume", 1),
                                      ("stratified", 10)])
@pytest.mark.parametrize("channels", [1, 2, 37, 512, 2048])
def test_forward_and_backward_equal_reference(plan, sampler, k, channels):
    rng = np.random.default_rng(channels)
    n = plan.splats.shape[0]
    features = rng.standard_normal((n, channels)).astype(np.float32)
    background = rng.standard_normal(channels).astype(np.float32)
    sel = select(plan, sampler, k)
    h = sel.host()
    image = blend_forward(sel, device_rows(plan, features), channels, background).get()[:, :channels]
    scale = blend_ref.blend(h["ids"], np.abs(h["weights"]), np.abs(features), h["t_rem"], np.abs(background))
    assert_rows_close(image, blend_ref.blend(h["ids"], h["weights"], features, h["t_rem"], background),
                      scale.max(axis=1, keepdims=True))

    dimage = rng.standard_normal((sel.n_rays, channels)).astype(np.float32)
    dF = blend_backward(sel, device_rows(plan, dimage), channels).get()[:, :channels]
    want = np.zeros((n, channels))
    valid = h["ids"] >= 0
    rays = np.broadcast_to(np.arange(sel.n_rays)[:, None], h["ids"].shape)[valid]
    np.add.at(want, h["ids"][valid], h["weights"][valid, None].astype(np.float64) * dimage[rays])
    np.testing.assert_allclose(dF, want, rtol=RTOL, atol=RTOL * np.abs(want).max())
    assert np.abs(dF[np.setdiff1d(np.arange(n), h["ids"][valid])]).max(initial=0) == 0


@pytest.mark.parametrize("owners_per_core,channels", [(1, 64), (3, 64), (1000, 64), ("gather", 64),
                                                     ("gather", 512)])
def test_backward_bytes_do_not_depend_on_the_kernel(plan, monkeypatch, owners_per_core, channels):
    """The CPU scatter sums each Gaussian's entries in ray order whichever work-item owns it: any
    number of owners (up to one per Gaussian), and the gather over the transpose (4 vectors a
    work-item at 64 channels, a whole row at 512), give the bytes of the default, run after run."""
    rng = np.random.default_rng(5)
    sel = select(plan, "volume", 1)
    assert blend_stage.scatters(sel)              # a whole image has more rays than Gaussians
    dimage = device_rows(plan, rng.standard_normal((sel.n_rays, channels)).astype(np.float32))
    first = blend_backward(sel, dimage, channels).get()
    if owners_per_core == "gather":
        monkeypatch.setattr(blend_stage, "scatters", lambda sel, backward_index=None: False)
    else:
        monkeypatch.setattr(blend_stage, "OWNERS_PER_CORE", owners_per_core)
    second = blend_backward(sel, dimage, channels).get()
    assert first.tobytes() == second.tobytes()
    assert np.abs(first).max() > 0


@pytest.mark.parametrize("acc_floats", [16, 64, 256])
def test_register_chunks_do_not_change_the_bytes(plan, monkeypatch, acc_floats):
    """Blend, backward gather and fused V-Render accumulate a row RV vectors at a time, RV from
    the device's register budget (ACC_FLOATS): 1, 4 or 16 float16 vectors give the same bytes."""
    rng = np.random.default_rng(9)
    features = device_rows(plan, rng.standard_normal((plan.splats.shape[0], 512)).astype(np.float32))
    sel = select(plan, "quantile", 10)

    def outputs():
        image = blend_forward(sel, features, 512)
        with monkeypatch.context() as m:
            m.setattr(blend_stage, "scatters", lambda sel, backward_index=None: False)
            grad = blend_backward(sel, image, 512)
        return image.get(), grad.get(), render_fused(plan, features, 512)[0]

    want = outputs()
    rt = plan.runtime
    monkeypatch.setattr(type(rt), "accumulator_floats", property(lambda self: acc_floats))
    monkeypatch.setattr(rt, "_programs", {})          # built again with the new ACC_FLOATS
    for got, expected in zip(outputs(), want):
        np.testing.assert_array_equal(got, expected)
    assert np.abs(want[1]).max() > 0


@pytest.mark.parametrize("part", ["all", "rows"])
def test_owner_bounds_split_the_entries_evenly(plan, monkeypatch, part):
    """The scatter's owner ranges cover g0..g1 (0..N, or a row part's rows) in order and hold about
    equal numbers of the entries of those Gaussians: each within two histogram bins' entries of
    total / owners (a part's ends cut bins)."""
    monkeypatch.setattr(blend_stage, "OWNER_BINS", 64)
    sel = select(plan, "quantile", 6)
    h = sel.host()
    g0, g1 = (0, sel.n_gaussians) if part == "all" else (sel.n_gaussians // 5, sel.n_gaussians * 3 // 4)
    ids = h["ids"][(h["ids"] >= g0) & (h["ids"] < g1)]
    for owners in (1, 2, 5):
        bounds = blend_stage.owner_bounds(sel, owners, g0, g1)
        assert bounds[0] == g0 and bounds[-1] == g1 and len(bounds) == owners + 1
        assert (np.diff(bounds) >= 0).all()
        per_owner = np.histogram(ids, bins=bounds)[0]
        shift = max(0, int(np.ceil(np.log2(sel.n_gaussians / 64))))
        worst_bin = np.bincount(ids >> shift).max()
        assert per_owner.sum() == len(ids)
        assert np.abs(per_owner - len(ids) / owners).max() <= (1 if part == "all" else 2) * worst_bin


def test_volume_selection_blend_equals_fused(plan):
    rng = np.random.default_rng(6)
    features = rng.standard_normal((plan.splats.shape[0], 40)).astype(np.float32)
    fused, _, _ = render_fused(plan, device_rows(plan, features), 40)
    sel = select(plan, "volume", 1)
    image = blend_forward(sel, device_rows(plan, features), 40).get()[:, :40]
    np.testing.assert_allclose(image.reshape(fused.shape), fused, rtol=1e-6, atol=1e-6)


def test_pixel_subset_blend_equals_full_rows(plan):
    rng = np.random.default_rng(7)
    features = device_rows(plan, rng.standard_normal((plan.splats.shape[0], 16)).astype(np.float32))
    pixels = rng.integers(0, [plan.width, plan.height], (100, 2))
    full = blend_forward(select(plan, "topk", 4), features, 16).get()
    sub = blend_forward(select(plan, "topk", 4, pixels), features, 16).get()
    np.testing.assert_array_equal(sub, full[pixels[:, 1] * plan.width + pixels[:, 0]])


@pytest.mark.parametrize("sampler", ["quantile", "topk", "stratified"])
@pytest.mark.parametrize("channels,subset", [(3, False), (37, True), (512, False), (2048, True)])
def test_select_and_blend_equals_select_then_blend(plan, sampler, channels, subset):
    """select_and_blend runs the selection kernel with the blend fused in (CPU shapes): the same
    selection and the same image bytes as the two kernels, also with a background and for a pixel
    subset, and its selection blends again as select's does.

    Bytes on PoCL. Intel's CPU runtime compiles the selection arithmetic of the fused build apart
    and differs in the last bits (up to 1e-6 absolute here): within 1e-5 of the largest value."""
    same = (np.testing.assert_array_equal if "Portable Computing Language" in plan.runtime.device.platform.name
            else lambda got, want, err_msg="": np.testing.assert_allclose(
                got, want, rtol=0, atol=1e-5 * max(float(np.abs(want).max(initial=0)), 1.0), err_msg=err_msg))
    rng = np.random.default_rng(channels)
    features = device_rows(plan, rng.standard_normal((plan.splats.shape[0], channels)).astype(np.float32))
    background = rng.standard_normal(channels).astype(np.float32)
    pixels = rng.integers(0, [plan.width, plan.height], (300, 2)) if subset else None
    eager = select(plan, sampler, 10, pixels)
    want = blend_forward(eager, features, channels, background).get()
    fused, got = select_and_blend(plan, sampler, 10, pixels, features, channels, background)
    same(got.get(), want)
    same(blend_forward(fused, features, channels).get(), blend_forward(eager, features, channels).get())
    for key, value in eager.host().items():
        same(fused.host()[key], value, err_msg=key)


@pytest.mark.parametrize("shift", [0, 1, 4])
def test_outputs_at_any_alignment(plan, shift, monkeypatch):
    """Blend and fused V-Render stream large images with non-temporal stores where a row's vectors
    are aligned and store them plainly where not (here every image streams): images written into
    host memory starting 0, 4 or 16 bytes past a 64-byte boundary (used in place on CPU devices)
    are the bytes of plainly stored ones."""
    rng = np.random.default_rng(8)
    features = device_rows(plan, rng.standard_normal((plan.splats.shape[0], 48)).astype(np.float32))
    sel = select(plan, "quantile", 5)
    want = blend_forward(sel, features, 48).get()
    want_fused = render_fused(plan, features, 48)[0]
    rt, rows = plan.runtime, (sel.n_rays, 48)
    monkeypatch.setattr(memory, "STREAM_MIN_BYTES", 0)

    def misaligned(shape):
        n = int(np.prod(shape))
        base = np.zeros(n + 32, np.float32)
        start = (-base.ctypes.data // 4) % 16 + shift        # 64-byte boundary, then shift floats
        return base[start:start + n].reshape(shape)

    host = misaligned(rows)
    with shared_array(rt, host, "w") as out:
        blend_forward(sel, features, 48, out=out)
    np.testing.assert_array_equal(host, want)
    host = misaligned((plan.height, plan.width, 48))
    np.testing.assert_array_equal(render_fused(plan, features, 48, out=host)[0], want_fused)


def test_shape_errors(plan):
    sel = select(plan, "quantile", 3)
    n = sel.n_gaussians
    with pytest.raises(ValueError, match="features"):
        blend_forward(sel, device_rows(plan, np.zeros((3, 32), np.float32)), 16)
    with pytest.raises(ValueError, match=r"features must be rows of the \d+ Gaussians"):
        blend_forward(sel, device_rows(plan, np.zeros((3, 16), np.float32)), 16, row0=n - 2)
    with pytest.raises(ValueError, match="dimage"):
        blend_backward(sel, device_rows(plan, np.zeros((5, 16), np.float32)), 16)
    with pytest.raises(ValueError, match=r"dF must be rows"):
        blend_backward(sel, device_rows(plan, np.zeros((sel.n_rays, 16), np.float32)), 16, row0=1, n_rows=n)
    with pytest.raises(ValueError, match="pass it as out"):
        blend_forward(sel, device_rows(plan, np.zeros((n, 16), np.float32)), 16, accumulate=True)


def test_rows_to_half_rounds_as_numpy(plan):
    """The gradient of a float16 table is rounded on the device: to nearest even, as numpy's cast,
    overflow to infinity and subnormals included."""
    rt = plan.runtime
    rng = np.random.default_rng(9)
    values = np.concatenate([rng.standard_normal(4000) * 10.0 ** rng.integers(-9, 6, 4000),
                             [0.0, -0.0, 65504.0, 65520.0, 1e6, -1e6, 6e-8, 3e-8, 2.98e-8, 1 + 2 ** -11,
                              1 + 3 * 2 ** -11, np.inf, -np.inf]]).astype(np.float32).reshape(-1, 1)
    out = memory.device_empty(rt, values.shape, np.float16)
    got = blend_stage.rows_to_half(rt, memory.to_device(rt, values), out).get()
    assert got.tobytes() == values.astype(np.float16).tobytes()
    with pytest.raises(ValueError, match="float16 out"):
        blend_stage.rows_to_half(rt, memory.to_device(rt, values), memory.device_empty(rt, values.shape))


def row_split(n: int) -> list[tuple[int, int]]:
    """Three unequal row parts of n rows, none empty."""
    return [(0, n // 3), (n // 3, n // 3 + n // 4), (n // 3 + n // 4, n)]


@pytest.mark.parametrize("sampler,k", [("quantile", 10), ("volume", 1), ("topk", 6)])
@pytest.mark.parametrize("channels,half", [(37, False), (512, False), (48, True)])
@pytest.mark.parametrize("launch", ["cpu", "gpu"])
def test_row_parts_add_up_to_the_whole_table(plan, monkeypatch, sampler, k, channels, half, launch):
    """A table in row parts: each part's blend equals the twin of that part (entries of other
    Gaussians blend nothing), the parts accumulated into one image equal the whole table's blend
    to float rounding, the first blend fused with its selection (select_and_blend) or not; each part's dF is
    the whole table's rows of dF, byte for byte (scatter and gather, half tables' float rows)."""
    monkeypatch.setattr(plan.runtime, "gpu_shaped", launch == "gpu")
    rng = np.random.default_rng(channels)
    n = plan.splats.shape[0]
    cstride = channel_layout(channels)[2]
    features = padded_rows(rng.standard_normal((n, channels)).astype(np.float32), cstride)
    table = features.astype(np.float16) if half else features
    background = rng.standard_normal(channels).astype(np.float32)
    rt = plan.runtime
    whole = blend_forward(select(plan, sampler, k), cla.to_device(rt.queue, table), channels, background).get()
    for fuse in (False, True):
        sel = None if fuse else select(plan, sampler, k)
        image = memory.device_empty(rt, (whole.shape[0], cstride))
        for i, (r0, r1) in enumerate(row_split(n)):
            part = cla.to_device(rt.queue, table[r0:r1])
            if sel is None:                    # the first part's blend made with its selection
                sel, alone = select_and_blend(plan, sampler, k, None, part, channels)
            else:
                alone = blend_forward(sel, part, channels, row0=r0)
            h = sel.host()
            want = blend_ref.blend(h["ids"], h["weights"], table[r0:r1, :channels], row0=r0)
            scale = blend_ref.blend(h["ids"], np.abs(h["weights"]), np.abs(table[:, :channels]))
            assert_rows_close(alone.get()[:, :channels], want, scale.max(axis=1, keepdims=True))
            if fuse and i == 0:
                select_and_blend(plan, sampler, k, None, part, channels, background, out=image)
            else:
                blend_forward(sel, part, channels, None if i else background, out=image, row0=r0, accumulate=i > 0)
        scale = np.abs(whole).max(axis=1, keepdims=True)
        assert_rows_close(image.get()[:, :channels], whole[:, :channels], scale, rtol=1e-6)
    dimage = cla.to_device(rt.queue, rng.standard_normal((sel.n_rays, cstride)).astype(np.float32))
    dF = blend_backward(sel, dimage, channels).get()
    for r0, r1 in row_split(n):
        part = blend_backward(sel, dimage, channels, row0=r0, n_rows=r1 - r0).get()
        assert part.tobytes() == dF[r0:r1].tobytes()


@pytest.mark.parametrize("half", [False, True])
def test_fused_volume_render_in_row_parts(plan, half):
    """The fused V-Render of a table in row parts: each part equals its twin (the other rows blend
    nothing), and the parts accumulated equal the whole table's render to float rounding."""
    from qr_cl.stages import vrender_ref
    rng = np.random.default_rng(4)
    n, channels = plan.splats.shape[0], 40
    cstride = channel_layout(channels)[2]
    features = padded_rows(rng.standard_normal((n, channels)).astype(np.float32), cstride)
    table = features.astype(np.float16) if half else features
    background = rng.standard_normal(channels).astype(np.float32)
    rt = plan.runtime
    meta = plan.meta()
    whole = render_fused(plan, cla.to_device(rt.queue, table), channels, background)[0].copy()
    out = memory.host_empty((plan.height, plan.width, cstride))
    for i, (r0, r1) in enumerate(row_split(n)):
        part = cla.to_device(rt.queue, table[r0:r1])
        alone = render_fused(plan, part, channels, row0=r0)[0]
        want = vrender_ref.vrender(meta, meta["tile_ranges"], meta["flatten_ids"], table[r0:r1, :channels],
                                   plan.width, plan.height, row0=r0)[0]
        np.testing.assert_allclose(alone, want, rtol=1e-5, atol=1e-5 * np.abs(want).max())
        image = render_fused(plan, part, channels, None if i else background, out=out, row0=r0, accumulate=i > 0)[0]
    np.testing.assert_allclose(image, whole, rtol=1e-6, atol=1e-6 * np.abs(whole).max())
