"""Portability (issue 12, "Prove any OpenCL driver"): results that must not depend on the device.

A float -> int conversion of an out-of-range value is undefined in OpenCL C (INT_MIN on x86,
saturated on GPUs), and so are ``max``/``min`` of an infinite or NaN argument. project.cl clamps
in float before converting and uses fmax, so an extreme Gaussian is culled or drawn the same way
everywhere, as its float64 twin (qr_cl.stages.project_ref) says.
"""
import numpy as np
import pytest

from qr_cl.render import rasterize_plan
from qr_cl.runtime import runtime, to_device
from qr_cl.scene import look_at
from qr_cl.stages import binning_ref, project, project_ref

W, H = 96, 72
RADIUS_MAX = project_ref.RADIUS_MAX


def extreme_scene():
    """(means, quats, scales, opacities, expectation per Gaussian) for a camera at the origin
    looking down +z (fx = 80 px, world axes = camera axes, so axis-aligned Gaussians keep an
    exactly diagonal 2D covariance): "drawn" (covers the whole image, radii RADIUS_MAX), "band"
    (radius RADIUS_MAX along its long axis only, binned across the whole image along it), "culled", or
    "normal"."""
    near_z = 0.0100001                     # just inside the near plane (0.01)
    rows = [
        # (mean, scale, expectation)
        # radius ~6e10 px (float32: mid*mid - det = inf - inf; the tile rectangle's upper corner
        # 3.7e9 tiles is beyond INT_MAX): covers the image
        ((0, 0, 4), (1e9, 1e9, 1e9), "drawn"),
        # anisotropic: float32 radius +inf (mid * mid overflows), float64 ~6e10: a band of tiles
        # across the image (the opacity-aware extent of the thin axis is a few px)
        ((0, 0, 4), (1e9, 1e-3, 1e-3), "band"),
        ((0.2, -0.1, 3), (1e-3, 1e9, 1e-3), "band"),
        # projected mean 5e10 px to the right, radius 6e10 px: still covers the image
        ((5e10 * 4 / 80, 0, 4), (1e9, 1e9, 1e9), "drawn"),
        # projected means ~8e29 px (near-zero depth, inside the near plane): culled
        ((1e26, 0, near_z), (0.1, 0.1, 0.1), "culled"),
        ((-1e26, 1e26, near_z), (0.1, 0.1, 0.1), "culled"),
        ((1e26, 0, near_z), (1e9, 1e-3, 1e-3), "culled"),    # radius ~1e13 px << 8e29 px
        # projected mean beyond FLT_MAX px (+inf in float32) with a float32 radius of +inf
        ((1e37, 0, near_z), (1e9, 1e-3, 1e-3), "culled"),
        ((0, -1e37, near_z), (0.1, 0.1, 0.1), "culled"),
        # projected mean 5e10 px away with an ordinary radius: culled
        ((5e10 * 4 / 80, 0, 4), (0.1, 0.1, 0.1), "culled"),
        ((0, -5e10 * 4 / 80, 4), (0.1, 0.1, 0.1), "culled"),
        # ordinary Gaussians, so the scene is not all edge cases
        ((0.1, 0.2, 2), (0.05, 0.02, 0.03), "normal"),
        ((-0.4, 0.1, 3), (0.1, 0.1, 0.02), "normal"),
    ]
    means = np.array([r[0] for r in rows], np.float32)
    scales = np.array([r[1] for r in rows], np.float32)
    quats = np.tile(np.array([1, 0, 0, 0], np.float32), (len(rows), 1))
    opacities = np.full(len(rows), 0.5, np.float32)
    return means, quats, scales, opacities, [r[2] for r in rows]


@pytest.fixture(scope="module")
def extreme():
    means, quats, scales, opacities, expect = extreme_scene()
    cam = look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 80.0, 80.0, W, H)
    assert np.array_equal(cam.viewmat[:3, :3], np.eye(3))
    plan = rasterize_plan(means, quats, scales, opacities, cam.viewmat, cam.K, W, H)
    rt = runtime()
    _, _, footprints, touched, _ = project(rt, *(to_device(rt, a) for a in (means, quats, scales, opacities)),
                                      cam.viewmat, cam.K, W, H, 0.01, 1e10)
    with np.errstate(all="ignore"):
        twin = project_ref.project(means, quats, scales, opacities, cam.viewmat, cam.K, W, H)
    return plan, plan.meta(), footprints.get().reshape(-1, 16)[:, :4], touched.get(), twin, expect


def test_extreme_gaussians_are_culled_or_drawn_as_the_twin_says(extreme):
    plan, meta, rects, touched, twin, expect = extreme
    tiles_x, tiles_y = (W + 15) // 16, (H + 15) // 16
    for i, what in enumerate(expect):
        got = (tuple(int(r) for r in meta["radii"][i]), tuple(rects[i]), int(touched[i]))
        want = (tuple(int(r) for r in twin["radii"][i]), tuple(twin["rects"][i]), int(twin["tiles_touched"][i]))
        if what == "normal":
            assert min(got[0]) > 0 and np.abs(np.subtract(got[0], want[0])).max() <= 1 and got[1:] == want[1:], \
                (i, got, want)
        else:
            assert got == want, f"Gaussian {i} ({what}): kernel {got}, twin {want}"
        if what == "drawn":
            assert got == ((RADIUS_MAX, RADIUS_MAX), (0, 0, tiles_x, tiles_y), tiles_x * tiles_y), (i, got)
        if what == "band":                       # long along one axis, a few px across the other
            x0, y0, x1, y1 = got[1]
            assert max(got[0]) == RADIUS_MAX and 0 < min(got[0]) < 20 and 0 < got[2] < tiles_x * tiles_y, (i, got)
            assert (x0, x1) == (0, tiles_x) or (y0, y1) == (0, tiles_y), (i, got)
        if what == "culled":
            assert got == ((0, 0), (0, 0, 0, 0), 0), (i, got)


def test_extreme_gaussians_are_binned_as_the_twin_says(extreme):
    plan, meta, _, _, twin, _ = extreme
    assert plan.n_keys == int(twin["tiles_touched"].sum())
    ranges, ids = binning_ref.bin_and_sort(twin, W, H)
    np.testing.assert_array_equal(meta["tile_ranges"], ranges)
    np.testing.assert_array_equal(meta["flatten_ids"], ids)


def test_twin_radii_are_clamped_not_wrapped():
    """The twin's int32 radii come from a float clamp too (numpy's out-of-range cast is
    undefined as well)."""
    means, quats, scales, opacities, _ = extreme_scene()
    cam = look_at([0, 0, 0], [0, 0, 1], [0, -1, 0], 80.0, 80.0, W, H)
    with np.errstate(all="ignore"):
        twin = project_ref.project(means, quats, scales, opacities, cam.viewmat, cam.K, W, H)
    assert twin["radii"].shape == (len(means), 2) and twin["radii"].min() >= 0 and twin["radii"].max() == RADIUS_MAX
