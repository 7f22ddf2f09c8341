"""Scenes and comparisons against the float64 twins (qr_cl.stages.*_ref) shared by the stage
tests (projection, V-Render) and the render tests: a hostile scene with edge cases in front of a
camera at the origin, and the kernel render beside the twins' render of the kernel's own tile lists."""
import numpy as np

import qr_cl
from qr_cl.scene import Gaussians, look_at
from qr_cl.stages import project_ref, vrender_ref

W, H = 96, 72


def hostile_scene(n=600, seed=0, degree=0) -> Gaussians:
    """Random Gaussians in front of a camera at the origin looking down +z, plus edge cases:
    behind the camera, at the near plane, huge (covering the image) and tiny ones."""
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform(-2, 2, (n, 2)), rng.uniform(1, 6, n)]
    scales = np.exp(rng.uniform(-4, -1, (n, 3)))
    means[:20, 2] = -rng.uniform(0.1, 3, 20)                 # behind the camera
    means[20:30, 2] = 0.01 + rng.choice([-1, 1], 10) * 2e-4  # straddling the near plane (0.01)
    means[20:30, :2] *= 0.005
    scales[30:35] = rng.uniform(3, 10, (5, 3))               # huge: covers the whole image
    means[30:35] = [[0, 0, 4]] * 5
    scales[35:60] = 1e-5                                     # tiny
    q = rng.normal(size=(n, 4))
    sh = rng.normal(0, 0.6, (n, (degree + 1) ** 2, 3))
    return Gaussians(means.astype(np.float32), (q / np.linalg.norm(q, axis=1, keepdims=True)).astype(np.float32),
                     scales.astype(np.float32), rng.uniform(0.05, 1, n).astype(np.float32), sh.astype(np.float32))


def origin_camera():
    return look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 80.0, 82.0, W, H)


def assert_projection_matches(meta, proj):
    assert meta["radii"].shape == proj["radii"].shape == (len(proj["radii"]), 2)
    vis = proj["radii"][:, 0] > 0
    assert ((meta["radii"] > 0) == (proj["radii"] > 0)[:, :1]).all(), "both radii are 0 exactly when culled"
    mismatch = (meta["radii"] != proj["radii"]).any(1)
    # a radius may differ only where float32 and float64 round a square root to different ceilings
    assert mismatch.sum() <= max(1, int(0.002 * len(mismatch))), f"{mismatch.sum()} radii differ"
    both = vis & ~mismatch
    for key in ("means2d", "conics", "depths"):
        np.testing.assert_allclose(meta[key][both], proj[key][both], rtol=1e-4, atol=1e-4, err_msg=key)
    np.testing.assert_array_equal(meta["means2d"][~vis & ~mismatch], 0)


def render_both(g, features, cam, background=None):
    """The kernel render, and the reference V-Render of the kernel's own projection and tile
    lists (so the blend is compared without projection rounding; those are tested apart)."""
    img, alpha, meta = qr_cl.render_volume_fused(g.means, g.quats, g.scales, g.opacities, features,
                                                 cam.viewmat, cam.K, cam.width, cam.height,
                                                 background=background)
    proj = project_ref.project(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, cam.width, cam.height)
    rimg, ralpha, rdepth = vrender_ref.vrender(meta, meta["tile_ranges"], meta["flatten_ids"], features,
                                       cam.width, cam.height, background)
    return (img.numpy(), alpha.numpy(), meta), (rimg, ralpha, rdepth, proj)


def top_contributors(meta, width: int, height: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """gsplat's top contributors of a plan's meta (means2d, conics, opacities, tile_ranges,
    flatten_ids) from the V-Render twin: per pixel (row-major) the k largest weights alpha_i T_i
    (ties: the nearer first), in depth order, and those weights. Returns ids [P,k] (-1 padded)
    and weights [P,k] (0 padded)."""
    from qr_cl.stages import select_ref
    ids = np.full((width * height, k), -1, np.int32)
    weights = np.zeros((width * height, k), np.float32)
    tiles_x = -(-width // 16)
    for p in range(width * height):
        x, y = p % width, p // width
        start, end = meta["tile_ranges"][(y // 16) * tiles_x + x // 16]
        tile_ids = np.asarray(meta["flatten_ids"][start:end])
        pos, w, _ = select_ref.volume_select(select_ref.alphas(meta, tile_ids, np.array([[x, y]]))[0])
        keep = np.sort(np.lexsort((pos, -w))[:k])
        ids[p, :len(keep)], weights[p, :len(keep)] = tile_ids[pos[keep]], w[keep]
    return ids, weights
