"""Selection kernels (select.cl) against the numpy references of Algorithm 1, top-K and V-Render."""
from __future__ import annotations

import math

import numpy as np
import pytest

import qr_cl
from qr_cl.app.experiments.transmittance import transmittance_profile
from qr_cl.app.images import plot_transmittance_profiles
from qr_cl.render import rasterize_plan
from qr_cl.runtime import TILE
from qr_cl.stages import Selection, blend_ref, select, select_ref

RTOL = 1e-5


def assert_rows_close(got: np.ndarray, want: np.ndarray, rtol: float = RTOL) -> None:
    """|got - want| <= rtol * (largest |want| of the row), element-wise: relative error at the
    scale of each ray (a small weight inherits the absolute rounding of its alpha's exp)."""
    scale = np.abs(want).max(axis=-1, keepdims=True) if want.size else want
    bad = np.abs(got - want) > rtol * scale + 1e-12
    assert not bad.any(), f"{bad.sum()} elements differ, worst {np.abs(got - want)[bad].max()}"


def all_pixels(width: int, height: int) -> np.ndarray:
    ys, xs = np.mgrid[0:height, 0:width]
    return np.stack([xs.ravel(), ys.ravel()], 1)


def compare(plan, sel: Selection, pixels: np.ndarray, sampler: str, k: int) -> int:
    """Assert kernel == reference selection on every ray except near-boundary ones; return how
    many rays differ (their ids or counts)."""
    meta = plan.meta()
    got = sel.host()
    want = select_ref.select(meta, meta["tile_ranges"], plan.ids.get(), pixels, plan.width, sampler, k)
    width = max(got["ids"].shape[1], want["ids"].shape[1])
    pad = lambda a, v: np.pad(a, ((0, 0), (0, width - a.shape[1])), constant_values=v)
    ids_g, ids_w = pad(got["ids"], -1), pad(want["ids"], -1)
    same = (got["count"] == want["count"]) & (ids_g == ids_w).all(1)
    assert_rows_close(pad(got["weights"], 0)[same], pad(want["weights"], 0)[same])
    for name in ("t_walk", "t_sel", "t_rem"):
        np.testing.assert_allclose(got[name][same], want[name][same], rtol=RTOL, atol=1e-7)
    if sampler != "volume":
        assert got["count"].max(initial=0) <= k
        np.testing.assert_allclose(got["weights"].sum(1)[got["count"] > 0], 1, rtol=1e-5)
    margin = {"quantile": select_ref.quantile_margin, "stratified": select_ref.stratified_margin}
    if sampler in margin:       # a differing ray must have a transmittance at a boundary
        tiles_x = plan.tiles_x
        for x, y in pixels[~same]:
            start, end = meta["tile_ranges"][(y // TILE) * tiles_x + x // TILE]
            ids = plan.ids.get()[start:end]
            assert margin[sampler](select_ref.alphas(meta, ids, np.array([[x, y]]))[0], k) < 1e-5
    return int((~same).sum())


@pytest.fixture(scope="module")
def random_plan(random_scene):
    return rasterize_plan(*random_scene)


CASES = [("volume", 0), ("quantile", 1), ("quantile", 4), ("quantile", 10), ("quantile", 1000),
         ("topk", 1), ("topk", 10), ("topk", 1000), ("stratified", 1), ("stratified", 4),
         ("stratified", 10), pytest.param("stratified", 1000, marks=pytest.mark.slow)]


@pytest.mark.parametrize("sampler,k", CASES)
def test_kernel_equals_reference_random(random_plan, sampler, k):
    pixels = all_pixels(random_plan.width, random_plan.height)
    differing = compare(random_plan, select(random_plan, sampler, k or 1), pixels, sampler, k)
    assert differing <= len(pixels) // 1000, f"{differing} rays differ"


@pytest.mark.data
@pytest.mark.parametrize("scene", ["fox", "donut"])
def test_kernel_equals_reference_real(request, scene):
    if scene == "fox":
        g = request.getfixturevalue("fox")
        cam = qr_cl.orbit_cameras(g.means, 3, 320, 240)[1]
    else:
        g, cams = request.getfixturevalue("donut")
        cam = cams[0].resized(320, 240)
    plan = rasterize_plan(g.means, g.quats, g.scales, g.opacities, cam.viewmat, cam.K, cam.width, cam.height)
    pixels = np.random.default_rng(1).integers(0, [cam.width, cam.height], (600, 2))
    report = {}
    for sampler, k in [("volume", 0), ("quantile", 10), ("quantile", 40), ("topk", 10), ("stratified", 10)]:
        sel = select(plan, sampler, k or 1, pixels)
        assert sel.count.get().max() > 0, "the camera sees nothing"
        report[f"{sampler}{k or ''}"] = compare(plan, sel, pixels, sampler, k)
    print(f"{scene}: rays whose ids differ from the reference (of {len(pixels)}): {report}")
    assert sum(report.values()) <= len(pixels) // 100


def test_pixel_subset_equals_full_image_rows(random_plan):
    rng = np.random.default_rng(2)
    pixels = rng.integers(0, [random_plan.width, random_plan.height], (257, 2))
    rows = pixels[:, 1] * random_plan.width + pixels[:, 0]
    for sampler, k in [("quantile", 7), ("topk", 5), ("volume", 1), ("stratified", 6)]:
        full, sub = select(random_plan, sampler, k).host(), select(random_plan, sampler, k, pixels).host()
        for name in ("count", "t_walk", "t_sel", "t_rem"):
            np.testing.assert_array_equal(sub[name], full[name][rows])
        width = sub["ids"].shape[1]
        np.testing.assert_array_equal(sub["ids"], full["ids"][rows, :width])
        np.testing.assert_array_equal(sub["weights"], full["weights"][rows, :width])


def test_empty_pixels(random_scene):
    """Small Gaussians in the left half only: rays in the right half select nothing and have
    background weight 1; the left half does select Gaussians."""
    m, q, s, o, v, K, w, h = random_scene
    left = m[:, 0] / m[:, 2] < -0.1
    plan = rasterize_plan(m[left], q[left], np.full_like(s[left], 0.02), o[left], v, K, w, h)
    pixels = all_pixels(w, h)
    right = pixels[:, 0] >= w // 2 + 4
    for sampler in ("quantile", "topk", "volume"):
        sel = select(plan, sampler, 5, pixels).host()
        assert (sel["count"][right] == 0).all() and sel["count"][~right].sum() > 0
        assert (sel["t_rem"][right] == 1).all() and (sel["t_walk"][right] == 1).all()


def test_empty_pixel_list(random_plan):
    sel = select(random_plan, "quantile", 5, np.zeros((0, 2), np.int64))
    assert sel.n_rays == 0 and sel.host()["ids"].shape == (0, 0)


def test_gaussian_covering_whole_image():
    means = np.array([[0, 0, 3.0]], np.float32)
    quats = np.array([[1, 0, 0, 0]], np.float32)
    scales = np.full((1, 3), 50.0, np.float32)
    K = np.array([[40, 0, 24], [0, 40, 20], [0, 0, 1]], np.float32)
    plan = rasterize_plan(means, quats, scales, np.array([0.7], np.float32), np.eye(4, dtype=np.float32), K, 48, 40)
    for sampler, k in [("quantile", 1), ("quantile", 10), ("topk", 1), ("volume", 1)]:
        h = select(plan, sampler, k).host()
        assert (h["count"] == 1).all() and (h["ids"][:, 0] == 0).all()
        if sampler == "volume":
            np.testing.assert_allclose(h["weights"][:, 0], 0.7, rtol=2e-3)   # the tail of the Gaussian
        else:
            np.testing.assert_array_equal(h["weights"][:, 0], 1)
            assert (h["t_rem"] == 0).all()


def test_large_k_selects_what_volume_uses(random_plan):
    """With K beyond any list length top-K keeps every Gaussian V-Render blends."""
    vol, top = select(random_plan, "volume", 1).host(), select(random_plan, "topk", 1000).host()
    np.testing.assert_array_equal(vol["count"], top["count"])
    np.testing.assert_array_equal(vol["ids"], top["ids"][:, :vol["ids"].shape[1]])


@pytest.mark.parametrize("kwargs,match", [
    ({"sampler": "median"}, "sampler"), ({"k": 0}, "K must"), ({"k": -3}, "K must"),
    ({"k": 2.5}, "K must"), ({"pixels": [[0, 0], [70, 3]]}, "outside"),
    ({"pixels": [[0, -1]]}, "outside"), ({"pixels": [[0.5, 1.0]]}, "integer"),
    ({"pixels": [1, 2]}, "shape")])
def test_bad_input(random_plan, kwargs, match):
    args = {"sampler": "quantile", "k": 4, **kwargs}
    with pytest.raises(ValueError, match=match):
        select(random_plan, **args)


def test_rasterize_bad_input(random_scene):
    m, q, s, o, v, K, w, h = random_scene
    f = np.ones((len(m), 3), np.float32)
    with pytest.raises(ValueError, match="sampler"):
        qr_cl.rasterize(m, q, s, o, f, v, K, w, h, sampler="Quantile")
    with pytest.raises(ValueError, match="k must"):
        qr_cl.rasterize(m, q, s, o, f, v, K, w, h, sampler="topk", k=0)
    with pytest.raises(ValueError, match="outside"):
        qr_cl.rasterize(m, q, s, o, f, v, K, w, h, sampler="quantile", pixels=[[w, 0]])


def test_transmittance_profiles(random_plan, tmp_path):
    pixel = np.array([[20, 25]])
    profiles = {}
    for sampler in ("volume", "topk", "quantile"):
        sel = select(random_plan, sampler, 10, pixel)
        depths, t = transmittance_profile(sel, 0)
        h = sel.host()
        assert len(t) == h["count"][0] + 1 >= 2 and t[0] == 1
        assert (np.diff(t) < 0).all() and (np.diff(depths) >= 0).all()
        np.testing.assert_allclose(t[-1], h["t_sel"][0], atol=1e-5)
        profiles[sampler] = depths, t
    path = tmp_path / "fig3.png"
    plot_transmittance_profiles(profiles, str(path), "K = 10")
    assert path.stat().st_size > 1000


@pytest.mark.data
def test_quantile_converges_to_volume(fox):
    """Mean |Q-Render - V-Render| of the fox's RGB over rays V-Render hits, for K from 5 to 1000.
    V-Render is divided by its opacity 1 - T (Q-Render's weights sum to 1, App. C)."""
    cam = qr_cl.orbit_cameras(fox.means, 1, 320, 240)[0]
    plan = rasterize_plan(fox.means, fox.quats, fox.scales, fox.opacities, cam.viewmat, cam.K, 320, 240)
    pixels = np.random.default_rng(3).integers(0, [320, 240], (3000, 2))
    rgb = fox.rgb
    vol = select(plan, "volume", 1, pixels).host()
    hit = vol["count"] > 0
    v_img = blend_ref.blend(vol["ids"], vol["weights"], rgb)[hit] / (1 - vol["t_walk"][hit, None])
    errors = {}
    for k in (5, 10, 20, 40, 100, 1000):
        q = select(plan, "quantile", k, pixels).host()
        errors[k] = float(np.abs(blend_ref.blend(q["ids"], q["weights"], rgb)[hit] - v_img).mean())
    print("mean |Q - V| (fox RGB):", {k: f"{e:.5f}" for k, e in errors.items()})
    assert errors[1000] < errors[40] < errors[5]
    assert errors[1000] < 0.01


def test_stratified_boundaries_follow_the_fitted_normal():
    """Stratified-K's boundaries are the quantiles of N(mu, sigma) cut to [T_end, 1]: denser around
    the mean than Q-Render's uniform ones, uniform when sigma is 0, never crossed past K."""
    K, mu, sigma, t_end = 9, 0.5, 0.1, 0.05
    b = np.array([select_ref.stratified_boundary(k, K, mu, sigma, t_end) for k in range(K)])
    assert (np.diff(b) < 0).all() and 1 > b[0] and b[-1] > t_end
    steps = -np.diff(b)
    assert steps[K // 2 - 1] < steps[0] and steps[K // 2 - 1] < steps[-1]      # dense at the mean
    cdf = lambda x: 0.5 * (1 + math.erf((x - mu) / sigma / math.sqrt(2)))
    mass = np.array([cdf(1.0)] + [cdf(x) for x in b] + [cdf(t_end)])
    np.testing.assert_allclose(-np.diff(mass), (mass[0] - mass[-1]) / (K + 1), rtol=1e-4)   # equal mass
    np.testing.assert_allclose([select_ref.stratified_boundary(k, 3, 0.7, 0.0, 0.2) for k in range(3)],
                               [0.8, 0.6, 0.4], rtol=1e-6)
    assert select_ref.stratified_boundary(K, K, mu, sigma, t_end) == -1
