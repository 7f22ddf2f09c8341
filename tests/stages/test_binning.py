"""Binning (binning.cl: tile spans, keys, sort) against its float64 twin (qr_cl.stages.binning_ref),
and the host sort."""
import numpy as np
import pytest
import torch

import qr_cl
from qr_cl.render import rasterize_plan
from qr_cl.scene import Gaussians, look_at
from qr_cl.stages import binning_ref, host_sort, project_ref
from tests.twins import H, W, hostile_scene, origin_camera


def test_binning_matches_reference():
    g, cam = hostile_scene(seed=1), origin_camera()
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, W, H)
    proj = project_ref.project(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, W, H)
    ranges, ids = binning_ref.bin_and_sort(proj, W, H)
    assert plan.n_keys == len(ids) == proj["tiles_touched"].sum()
    np.testing.assert_array_equal(plan.ranges.get(), ranges)
    np.testing.assert_array_equal(plan.ids.get()[:plan.n_keys], ids)


def tilted_scene(n=150, seed=0) -> Gaussians:
    """Elongated, tilted Gaussians of all sizes in front of the origin camera: ellipses that leave
    many tiles of their bounding rectangle untouched, some taller than SPAN_ROWS tile rows at
    640x480 (their spans are computed again in the binning passes instead of stored)."""
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform(-1.5, 1.5, (n, 2)), rng.uniform(2, 5, n)]
    scales = np.c_[np.exp(rng.uniform(-3, 0.5, n)), np.exp(rng.uniform(-5, -3, (n, 2)))]
    q = rng.normal(size=(n, 4))
    return Gaussians(means.astype(np.float32), (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                     scales.astype(np.float32), rng.uniform(0.05, 1, n).astype(np.float32),
                     np.zeros((n, 1, 3), np.float32))


def test_tile_spans_drop_only_tiles_the_ellipse_never_blends():
    """Brute force, in float64: no pixel of a tile that a Gaussian's row spans leave out of its
    rectangle has sigma <= sigma_max there (so no pixel of it would blend the Gaussian), and the
    spans do leave tiles out."""
    g, cam = tilted_scene(), look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 500.0, 500.0, 640, 480)
    proj = project_ref.project(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, 640, 480)
    tiles_x = 40
    dropped = 0
    for i in np.flatnonzero(proj["radii"][:, 0] > 0):
        x0, y0, x1, y1 = proj["rects"][i]
        kept = {(ty, tx) for ty, a, b in project_ref.tile_spans(proj["means2d"][i], proj["conics"][i],
                                                                 proj["opacities"][i], proj["rects"][i], tiles_x)
                for tx in range(a, b)}
        a, b, c = proj["conics"][i]
        sigma_max = np.log(proj["opacities"][i] / qr_cl.runtime.ALPHA_MIN)
        for ty in range(y0, y1):
            for tx in range(x0, x1):
                if (ty, tx) in kept:
                    continue
                dropped += 1
                ys, xs = np.mgrid[ty * 16:ty * 16 + 16, tx * 16:tx * 16 + 16] + 0.5
                dx, dy = proj["means2d"][i, 0] - xs, proj["means2d"][i, 1] - ys
                sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
                assert sigma.min() > sigma_max, f"Gaussian {i} blends in dropped tile ({tx}, {ty})"
    rect_tiles = np.prod(proj["rects"][:, 2:] - proj["rects"][:, :2], axis=1)[proj["radii"][:, 0] > 0].sum()
    assert dropped > 0.2 * rect_tiles, (dropped, rect_tiles)


def test_binning_of_tall_tilted_ellipses_matches_reference():
    """Stored spans (rectangles of at most SPAN_ROWS rows) and spans computed again (taller ones)
    give the twin's tile lists, with fewer pairs than the rectangles. The twin bins the kernel's
    own splats: the float32 conic of a Gaussian hundreds of pixels wide differs from the float64
    one by ~1e-3, enough to move a span's end across a tile edge (the projection is tested apart)."""
    g, cam = tilted_scene(seed=1), look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 500.0, 500.0, 640, 480)
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, 640, 480)
    proj = project_ref.project(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, 640, 480)
    meta = plan.meta()
    np.testing.assert_array_equal(meta["radii"][:, 0] > 0, proj["radii"][:, 0] > 0)
    proj.update({k: meta[k].astype(np.float64) for k in ("means2d", "conics", "depths", "opacities")})
    rows = (proj["rects"][:, 3] - proj["rects"][:, 1])[proj["radii"][:, 0] > 0]
    assert (rows > 24).sum() >= 3 and (rows <= 24).sum() >= 30, "both kinds of rectangles"
    ranges, ids = binning_ref.bin_and_sort(proj, 640, 480)
    np.testing.assert_array_equal(plan.ranges.get(), ranges)
    np.testing.assert_array_equal(plan.ids.get()[:plan.n_keys], ids)
    rect_pairs = np.prod(proj["rects"][:, 2:] - proj["rects"][:, :2], axis=1)[proj["radii"][:, 0] > 0].sum()
    assert plan.n_keys < 0.8 * rect_pairs


def test_host_sort_is_stable_and_restores_torchs_thread_count():
    """The binning's host sort equals numpy's stable argsort (ties keep their index order) and
    leaves torch's thread count as it found it, also when the sort fails."""
    keys = torch.from_numpy(np.random.default_rng(0).integers(0, 50, 10_000).astype(np.int32))
    threads = torch.get_num_threads()
    sorted_keys, order = host_sort(keys)
    np.testing.assert_array_equal(order.numpy(), np.argsort(keys.numpy(), kind="stable"))
    np.testing.assert_array_equal(sorted_keys.numpy(), np.sort(keys.numpy()))
    with pytest.raises(RuntimeError):
        host_sort(keys, out=(torch.empty(3, dtype=torch.float64), torch.empty(3, dtype=torch.int64)))
    assert torch.get_num_threads() == threads
