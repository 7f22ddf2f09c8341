"""Training that touches only what its rays select: compact de-voxelization, per-view selections
gathered instead of recomputed, the step's loss equal to the full-table render's."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from qr_cl.app.scenes.folders import load_scene_folder
from qr_cl.app.training import trainer as trainer_module
from qr_cl.app.training.config import TrainConfig
from qr_cl.app.training.loss import contrastive_loss, cosine_logits, head_cosine_logits
from qr_cl.app.training.rays import rays_loss, sample_rays, scene_loss, step_rays
from qr_cl.app.training.trainer import Trainer, conv_thread_count, train
from qr_cl.backbone import GSNet, VoxelConfig, conv, devoxelize, minkunet14
from qr_cl.render import SelectionCache, rasterize
from qr_cl.scene import Gaussians

SMALL = dict(stem_channels=8, stem_kernel=3, enc_channels=(8, 16, 16), enc_blocks=(1, 1, 1),
             dec_channels=(16, 8, 8), dec_blocks=(1, 1, 1))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def scene(tiny_room):
    return tiny_room


def random_gaussians(n: int, seed: int) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians.from_rgb(
        torch.rand(n, 3, generator=g) * 0.6, torch.randn(n, 4, generator=g), torch.rand(n, 3, generator=g) * 0.03 + 1e-3,
        torch.rand(n, generator=g) * 0.9 + 0.05, torch.rand(n, 3, generator=g))


@pytest.mark.parametrize("shape,reduce", [("center", "max"), ("volume", "max"), ("volume", "mean")])
def test_devoxelize_rows_are_rows_of_the_full_result(shape, reduce):
    batch = GSNet(8, VoxelConfig(grid_size=0.05, sample_shape=shape), minkunet14(7, **SMALL)).prepare(
        [random_gaussians(120, 1), random_gaussians(80, 2)])
    voxels = torch.randn(batch.coords.shape[0], 5, generator=torch.Generator().manual_seed(3))
    rows = torch.tensor([199, 0, 57, 57, 120, 3])
    assert torch.equal(devoxelize(voxels, batch, reduce, rows), devoxelize(voxels, batch, reduce)[rows])
    assert devoxelize(voxels, batch, reduce, torch.zeros(0, dtype=torch.int64)).shape == (0, 5)
    with pytest.raises(ValueError, match="rows"):
        devoxelize(voxels, batch, reduce, torch.tensor([200]))


@pytest.mark.parametrize("shape,reduce", [("center", "max"), ("volume", "max"), ("volume", "mean")])
def test_head_of_blended_head_inputs_is_the_blend_of_the_features(shape, reduce):
    """Weighted sums of head_inputs rows mapped by head_matrix equal the same weighted sums of
    the rows of forward (values, and gradients w.r.t. every parameter): rendering D + 1 channels
    and applying the head to the rays gives the rays of the unit features."""
    torch.manual_seed(0)
    net = GSNet(16, VoxelConfig(grid_size=0.05, sample_shape=shape), minkunet14(7, **SMALL), reduce=reduce).eval()
    batch = net.prepare(random_gaussians(150, 4))
    rows = torch.tensor([5, 149, 0, 77, 77])
    weights = torch.rand(6, len(rows), generator=torch.Generator().manual_seed(1))
    weights[0] = torch.tensor([1.0, 0, 0, 0, 0])            # a ray of one Gaussian: its own feature
    probe = torch.randn(6, 16, generator=torch.Generator().manual_seed(2))
    grads = []
    for rays in (lambda: weights @ net(batch)[rows],
                 lambda: weights @ net.head_inputs(batch, rows) @ net.head_matrix().T):
        net.zero_grad()
        value = rays()
        (value * probe).sum().backward()
        grads.append((value.detach(), [p.grad.clone() for p in net.parameters() if p.grad is not None]))
    (want, want_grads), (got, got_grads) = grads
    assert net.head_inputs(batch, rows).shape == (len(rows), SMALL["dec_channels"][-1] + 1)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(got[0], net(batch)[rows[0]].detach(), rtol=1e-5, atol=1e-6)
    assert len(got_grads) == len(want_grads) > 2 and want_grads[-2].abs().sum() > 0
    for g, w in zip(got_grads, want_grads):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-5)


def _cfg(scene, out, **kw) -> TrainConfig:
    base = dict(scenes=[str(scene)], out=str(out), steps=5, views=3, rays=200, net="tiny", lr=1e-2, grid_size=0.2,
                k=8, checkpoint_every=100, plateau_interval=4)
    base.update(kw)
    return TrainConfig(**base)


@pytest.mark.parametrize("sampler,k", [("quantile", 8), ("volume", 0)])
def test_step_rays_gathered_equal_recomputed(scene, sampler, k):
    data = load_scene_folder(scene)
    cfg = _cfg(scene, "-", sampler=sampler, k=k)
    cache = SelectionCache(1 << 30)
    for seed in range(2):
        kept = step_rays(data, cfg, np.random.default_rng(seed), cache)
        fresh = step_rays(data, cfg, np.random.default_rng(seed))
        np.testing.assert_array_equal(kept.rows, fresh.rows)
        for name, value in kept.selection.host().items():
            np.testing.assert_array_equal(value, fresh.selection.host()[name], err_msg=name)
        assert kept.n_rays == 3 * 200 and 0 < kept.touched < 1
    assert 0 < len(cache) <= len(data.frames) and cache.nbytes > 0 and cache.hits > 0
    full = SelectionCache(1)                  # no room for a whole view: its rays are selected afresh
    step_rays(data, cfg, np.random.default_rng(0), full)
    assert full.nbytes == 0 and len(full) == 0


def test_compact_loss_equals_the_full_table_render(scene):
    """The step's loss from the compact table equals the loss of every view rendered with
    rasterize from the whole [N, C] table (the previous path), and so do the gradients."""
    data = load_scene_folder(scene)
    cfg = _cfg(scene, "-")
    full = F.normalize(torch.randn(len(data.gaussians), data.feature_dim, generator=torch.Generator().manual_seed(0)),
                       dim=1).requires_grad_()
    rays = step_rays(data, cfg, np.random.default_rng(7))
    table = full.detach()[torch.from_numpy(rays.rows)].requires_grad_()
    compact = rays_loss(rays, table, cfg.temperature)
    rng = np.random.default_rng(7)
    usable = [i for i, f in enumerate(data.frames) if len(f.features) > 1]
    losses = []
    for v in rng.choice(usable, cfg.views, replace=cfg.views > len(usable)):
        frame, g = data.frames[int(v)], data.gaussians
        pixels, target = sample_rays(frame, cfg.rays, rng)
        cam = frame.camera
        image, _, _ = rasterize(g.means, g.quats, g.scales, g.opacities, full, cam.viewmat, cam.K, cam.width,
                                cam.height, sampler=cfg.sampler, k=cfg.k, pixels=pixels)
        losses.append(contrastive_loss(image, torch.from_numpy(target), torch.from_numpy(frame.features),
                                       cfg.temperature))
    reference = torch.stack(losses).mean()
    torch.testing.assert_close(compact, reference, rtol=1e-6, atol=0)
    compact.backward()
    reference.backward()
    expected = full.grad[torch.from_numpy(rays.rows)]          # float32 sums in another order: tolerance
    torch.testing.assert_close(table.grad, expected, rtol=1e-5, atol=1e-5 * float(expected.abs().max()))  # of its scale
    outside = np.setdiff1d(np.arange(len(data.gaussians)), rays.rows)
    assert not full.grad[torch.from_numpy(outside)].any()
    value, n = scene_loss(data, full.detach(), cfg, np.random.default_rng(7))
    assert n == rays.n_rays and torch.equal(value, compact.detach())


def test_same_seed_same_curve_with_or_without_kept_selections(scene, tmp_path):
    kept = train(_cfg(scene, tmp_path / "a"), progress=False)
    again = train(_cfg(scene, tmp_path / "b"), progress=False)
    fresh = train(_cfg(scene, tmp_path / "c", view_selections_mb=0), progress=False)
    assert kept.history == again.history == fresh.history
    assert kept.selections.nbytes > 0 and fresh.selections is None
    assert all(0 < t < 1 for t in kept.touched)


def test_a_full_view_cache_is_said_once_and_changes_nothing(scene, tmp_path):
    """Views whose whole-image selections the cache has no room for: one warning naming the
    bound, then none; the losses are those of a run that keeps every view."""
    kept = train(_cfg(scene, tmp_path / "a", steps=3), progress=False)
    full = Trainer(_cfg(scene, tmp_path / "b", steps=3))
    full.selections = SelectionCache(1)             # room for no whole view
    with pytest.warns(UserWarning, match=r"view_selections_mb=\d+ is full: 0 of the \d+ views"):
        full.train_step()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        full.train_step()
        full.train_step()
    full.close()
    assert full.selections.refused > 0 and full.history == kept.history
    assert kept.selections.refused == 0


def test_same_seed_same_curve_on_one_or_two_convolution_threads(scene, tmp_path, monkeypatch):
    """Every kernel map of the tiny room split in two blocks; train() gives the convolutions the
    process's cores (1, then 2): bitwise the same losses and weights."""
    monkeypatch.setattr(conv, "MIN_SPLIT_PAIRS", 64)
    runs = []
    for cores in (1, 2):
        monkeypatch.setattr(trainer_module, "process_cores", lambda cores=cores: cores)
        assert conv_thread_count() == cores
        runs.append(train(_cfg(scene, tmp_path / str(cores)), progress=False))
    one, two = runs
    assert one.history == two.history
    for a, b in zip(one.net.parameters(), two.net.parameters()):
        assert torch.equal(a, b)


def test_convolution_threads_times_torch_threads_fit_the_cores(monkeypatch):
    monkeypatch.setattr(trainer_module, "process_cores", lambda: 2)
    assert conv_thread_count() == 2            # one torch thread (this module's fixture)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    assert conv_thread_count() == 1
    monkeypatch.setattr(trainer_module, "process_cores", lambda: 1)
    assert conv_thread_count() == 1


def test_cosine_logits_match_normalize_and_its_gradient():
    gen = torch.Generator().manual_seed(0)
    rendered = torch.randn(9, 6, generator=gen, dtype=torch.float64)
    rendered[4] = 0                                           # a ray that selected nothing
    masks = [F.normalize(torch.randn(m, 6, generator=gen, dtype=torch.float64), dim=1) for m in (3, 2, 4)]
    sizes = [4, 0, 5]
    mine = rendered.clone().requires_grad_()
    ref = rendered.clone().requires_grad_()
    got = cosine_logits(mine, sizes, masks, 0.1)
    want = [F.normalize(r, dim=1) @ m.T / 0.1 for r, m in zip(torch.split(ref, sizes), masks)]
    for g, w in zip(got, want):
        torch.testing.assert_close(g, w, rtol=1e-12, atol=1e-12)
    weights = [torch.randn(w.shape, generator=gen, dtype=torch.float64) for w in want]
    sum((g * w).sum() for g, w in zip(got, weights)).backward()
    sum((g * w).sum() for g, w in zip(want, weights)).backward()
    torch.testing.assert_close(mine.grad, ref.grad, rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="split"):
        cosine_logits(mine, [4, 4], masks[:2], 0.1)


@pytest.mark.parametrize("channels", [12, 3])                 # more channels than sums have, and fewer
def test_head_cosine_logits_are_the_cosine_logits_of_the_headed_rays(channels):
    """head_cosine_logits(sums, head) equals cosine_logits(sums @ head.T) (float32, values and
    gradients w.r.t. sums and head), also for a ray whose headed feature is zero."""
    gen = torch.Generator().manual_seed(1)
    sums = torch.randn(9, 5, generator=gen)
    head = torch.randn(channels, 5, generator=gen)
    sums[4] = 0                                               # a ray that selected nothing
    masks = [F.normalize(torch.randn(m, channels, generator=gen), dim=1) for m in (3, 2, 4)]
    sizes = [4, 0, 5]
    probes = [torch.randn(n, len(m), generator=gen) for n, m in zip(sizes, masks)]
    results = []
    for logits in (lambda s, h: cosine_logits(s @ h.T, sizes, masks, 0.1),
                   lambda s, h: head_cosine_logits(s, h, sizes, masks, 0.1)):
        leaves = [sums.clone().requires_grad_(), head.clone().requires_grad_()]
        got = logits(*leaves)
        sum((g * p).sum() for g, p in zip(got, probes)).backward()
        results.append(([g.detach() for g in got], [t.grad for t in leaves]))
    (want, want_grads), (got, got_grads) = results
    for g, w in zip(got + got_grads, want + want_grads):
        torch.testing.assert_close(g, w, rtol=1e-4, atol=1e-4)
    assert got[1].shape == (0, 2) and torch.equal(got[2][0], torch.zeros(4))
    with pytest.raises(ValueError, match="head"):
        head_cosine_logits(sums, head[:, :4], sizes, masks, 0.1)


FREED_AND_AGAIN = """
import sys
import numpy as np
from qr_cl.app.process import keep_freed_memory
from qr_cl.app.timing import minor_faults
if sys.argv[1] == "keep" and not keep_freed_memory():
    print("no mallopt")
    sys.exit(0)
np.ones(16 << 20, np.float32)                 # 64 MB allocated, touched, freed
before = minor_faults()
np.ones(16 << 20, np.float32)                 # the same again
print(minor_faults() - before)
"""


def test_freed_memory_is_reused_without_page_faults():
    """keep_freed_memory (the CLI's train, demo and reproduce call it): a 64 MB array freed and
    allocated again reuses the pages (no faults), where by default it is a fresh mmap faulted in
    again (at least one fault per 2 MB huge page). Child processes: it changes the process."""
    import subprocess
    import sys

    def faults(mode: str) -> str:
        return subprocess.run([sys.executable, "-c", FREED_AND_AGAIN, mode], capture_output=True, text=True,
                              check=True).stdout.strip()
    kept = faults("keep")
    if kept == "no mallopt":
        pytest.skip("the C library has no mallopt (not glibc)")
    assert int(faults("default")) >= 32
    assert int(kept) <= 4


RELEASED = """
import numpy as np
from qr_cl.app.process import keep_freed_memory, release_freed_memory
from qr_cl.runtime import device_empty, host_empty, host_pool, runtime

def rss_mb():
    return int(open("/proc/self/status").read().split("VmRSS:")[1].split()[0]) >> 10

if not keep_freed_memory():
    print("no mallopt")
    raise SystemExit
rt = runtime()
host_empty((1 << 20,))                        # 4 MB in the host pool, free again
device_empty(rt, (1 << 20,))                  # 4 MB in the device pool, held
np.ones(16 << 20, np.float32)                 # 64 MB allocated, touched, freed: kept in the heap
kept = rss_mb()
held = (host_pool().nbytes, rt.pool.held_blocks)
if not release_freed_memory():
    print("no malloc_trim")
    raise SystemExit
print(kept - rss_mb(), held[0], held[1] > 0, host_pool().nbytes, rt.pool.held_blocks)
"""


def test_release_freed_memory_returns_what_the_process_kept():
    """release_freed_memory (the demo calls it between its phases): the 64 MB that keep_freed_memory
    kept in the heap go back to the system, and both pools drop their free buffers. A child
    process: keep_freed_memory changes the process."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", RELEASED], capture_output=True, text=True, check=True).stdout.split()
    if out[0] == "no":
        pytest.skip(f"the C library has {' '.join(out)} (not glibc)")
    returned_mb, host_before, device_held, host_after, device_after = out
    assert int(returned_mb) >= 48
    assert int(host_before) >= 4 << 20 and device_held == "True"
    assert int(host_after) == 0 and int(device_after) == 0
